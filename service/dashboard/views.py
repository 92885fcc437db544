"""What the dashboard's templates show: formatted numbers and times, the spec form's fields, its errors."""

from __future__ import annotations

import json
import math
import typing
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Optional

from jobs.schema import FINAL_STATES
from jobs.store import Job

#: Spec keys shown in the jobs table's "scene" column (shape aside).
SCENE_KEYS = ("n_particles", "e_n", "e_t", "volume_fraction", "seed")


def when(t: Optional[float]) -> str:
    """A UNIX time (s) as ``YYYY-MM-DD HH:MM:SS`` UTC, or an empty string."""
    if t is None:
        return ""
    return datetime.fromtimestamp(t, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


def duration(seconds: Optional[float]) -> str:
    """Seconds as ``2 h 05 min``, ``3 min 20 s``, ``12 s`` or ``0.4 s``; empty for None."""
    if seconds is None or not math.isfinite(seconds):
        return ""
    if seconds < 9.95:
        return f"{max(0.0, seconds):.1f} s"
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    if s >= 60:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s} s"


def sci(x: Optional[float]) -> str:
    """A number with three significant digits (``1.23e+06``), empty for None."""
    return "" if x is None else f"{x:.3g}"


def eta(job: Job) -> str:
    """Time left of a running job (its worker's estimate), else empty."""
    return duration(job.eta_s) if job.state == "running" and job.eta_s is not None else ""


def scene(spec: dict) -> str:
    """One line about a spec: shape, N, restitutions, volume fraction."""
    shape = spec.get("shape", "sphere")
    if shape == "ellipsoid":
        shape = f"ellipsoid xi={spec.get('elongation')}"
    return f"{shape}, " + ", ".join(f"{k.replace('n_particles', 'N').replace('volume_fraction', 'phi')}={spec.get(k)}"
                                    for k in SCENE_KEYS)


def live(job: Job) -> bool:
    return job.state not in FINAL_STATES


def percent(job: Job) -> int:
    """Progress in whole percent (100 once done)."""
    return 100 if job.state == "done" else int(max(0.0, min(1.0, job.progress or 0.0)) * 100)


def varying_keys(specs: list[dict]) -> list[str]:
    """Spec keys whose values differ between ``specs`` (the swept keys of a batch), in spec order."""
    if not specs:
        return []
    keys = list(specs[0])
    return [k for k in keys if any(json.dumps(s.get(k), sort_keys=True) != json.dumps(specs[0].get(k), sort_keys=True)
                                   for s in specs[1:])]


def show(value: Any) -> str:
    """A spec value as the form and the spec table show it (JSON for lists and null)."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    if isinstance(value, float) and abs(value) >= 1e5 and value == float(f"{value:.12e}"):
        mantissa, exponent = f"{value:.12e}".split("e")
        return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"   # 1e8, not 100000000.0
    return str(value)


# ---- the submit form -------------------------------------------------------------------------------------
@dataclass
class FormField:
    """One input of the spec form."""

    name: str
    kind: str                      # "select", "text" or "json"
    default: str                   # the spec's default, as shown
    help: str
    choices: list[str] = field(default_factory=list)
    optional: bool = False         # null is allowed (an empty input means null / the default)


def form_fields() -> list[FormField]:
    """The spec form, one field per key of the engine's SimulationSpec, defaults filled in."""
    from engine.setup.spec import SimulationSpec

    out = []
    for name, info in SimulationSpec.model_fields.items():
        ann = info.annotation
        args = typing.get_args(ann)
        optional = type(None) in args
        inner = [a for a in args if a is not type(None)] if optional else [ann]
        kind, choices = "text", []
        if typing.get_origin(inner[0]) is typing.Literal:
            kind, choices = "select", [str(c) for c in typing.get_args(inner[0])]
        elif inner[0] is bool:
            kind, choices = "select", ["true", "false"]
        elif typing.get_origin(inner[0]) in (list, typing.List):
            kind = "json"
        out.append(FormField(name, kind, show(info.default), info.description or "", choices, optional))
    return out


def spec_from_form(form: dict[str, str]) -> tuple[dict, dict[str, str]]:
    """The spec dict a submitted form means: an empty input takes the spec default (null where the
    default is null); JSON fields (species) are parsed here. Returns (spec, errors by field)."""
    spec, errors = {}, {}
    for f in form_fields():
        raw = (form.get(f.name) or "").strip()
        if not raw:
            continue
        if f.kind == "json":
            try:
                spec[f.name] = json.loads(raw)
            except ValueError as exc:
                errors[f.name] = (f"not valid JSON ({exc.msg} at character {exc.pos}); "
                                  "give a JSON list or leave it empty")
        else:
            spec[f.name] = raw
    return spec, errors


def errors_by_field(errors: list[dict]) -> tuple[dict[str, str], list[str]]:
    """Split :class:`jobs.specs.SpecRejected` errors into messages per spec field and spec-wide ones."""
    from engine.setup.spec import SimulationSpec

    per_field: dict[str, str] = {}
    general: list[str] = []
    for e in errors:
        loc = [x for x in e.get("loc", ()) if x != "body"]
        msg = str(e.get("msg", "")).removeprefix("Value error, ")
        if loc and loc[0] in SimulationSpec.model_fields:
            extra = ".".join(str(x) for x in loc[1:])
            text = f"{extra}: {msg}" if extra else msg
            per_field[loc[0]] = f"{per_field[loc[0]]}; {text}" if loc[0] in per_field else text
        else:
            general.append(msg)
    return per_field, general
