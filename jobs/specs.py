"""Admission of specs into the queue: validation with readable errors, cost limits, sweeps.

The engine's :class:`~engine.setup.spec.SimulationSpec` names field, value and allowed range in each
message. :class:`QueueSpec` adds one guard: a spec whose numbers overflow the derived-parameter
arithmetic (say ``box_length = 1e300``) is reported as invalid instead of crashing the caller.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Iterable, Optional

from pydantic import ConfigDict, ValidationError, model_validator

from engine.setup.limits import cost_excesses
from engine.setup.spec import SimulationSpec


class SpecRejected(ValueError):
    """A spec the queue does not accept; ``errors`` are ``{"loc": [...], "msg": str, "type": str}``."""

    def __init__(self, errors: list[dict]):
        super().__init__("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors))
        self.errors = errors


class QueueSpec(SimulationSpec):
    """The engine's spec, with arithmetic failures of its cross-field checks turned into errors."""

    model_config = ConfigDict(title="SimulationSpec")

    @model_validator(mode="wrap")
    @classmethod
    def _arithmetic_guard(cls, data: Any, handler):
        try:
            return handler(data)
        except (ArithmeticError, TypeError) as exc:  # overflow or division by zero in derived parameters
            raise ValueError(f"the spec's numbers cannot be evaluated ({exc}): use physically sized values")


def validation_errors(exc: ValidationError, prefix: Iterable = ()) -> list[dict]:
    """Pydantic errors as plain JSON-safe dicts, locations prefixed."""
    return [{"loc": [*prefix, *err["loc"]], "msg": err["msg"], "type": err["type"]} for err in exc.errors()]


def parse_spec(data: Any, loc: Iterable = ()) -> QueueSpec:
    """Validate a spec (dict); raise :class:`SpecRejected` naming the field and the limit."""
    try:
        return QueueSpec.model_validate(data)
    except ValidationError as exc:
        raise SpecRejected(validation_errors(exc, loc)) from None


def check_limits(spec: SimulationSpec, max_particle_steps: float, max_memory_bytes: float,
                 loc: Iterable = ()) -> None:
    """Refuse a spec whose estimated cost exceeds the configured limits (before it is queued)."""
    errors = [{"loc": [*loc], "type": f"limit_{e.kind}", "msg": e.message}
              for e in cost_excesses(spec, max_particle_steps, max_memory_bytes)]
    if errors:
        raise SpecRejected(errors)


def sweep_size(sweep: dict[str, list]) -> int:
    """Number of combinations of a sweep (product of the value counts)."""
    return math.prod(len(v) for v in sweep.values())


def expand_sweep(base: dict, sweep: dict[str, list]) -> list[dict]:
    """The cartesian product of the sweep values over the base spec, keys in the given order."""
    keys = list(sweep)
    return [{**base, **dict(zip(keys, combo))} for combo in itertools.product(*(sweep[k] for k in keys))]


def admit(items: list[Any], max_particle_steps: float, max_memory_bytes: float,
          loc: Optional[Iterable] = None) -> list[QueueSpec]:
    """Validate and cost-check several specs, collecting every error (loc gets the item index)."""
    specs, errors = [], []
    for i, item in enumerate(items):
        where = [*(loc or ()), i]
        try:
            spec = parse_spec(item, where)
            check_limits(spec, max_particle_steps, max_memory_bytes, where)
            specs.append(spec)
        except SpecRejected as exc:
            errors.extend(exc.errors)
    if errors:
        raise SpecRejected(errors)
    return specs
