"""The former place of engine/loops/status.py (the shared machinery moved to engine/loops/: the layer rule of
tests/test_imports.py). Importing this name gives that very module, so older imports and patches of it still work."""

import sys

from engine.loops import status as _module

sys.modules[__name__] = _module
