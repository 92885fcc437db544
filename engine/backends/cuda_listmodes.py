"""The former place of engine/loops/cuda_listmodes.py (the shared machinery moved to engine/loops/: the layer rule of
tests/test_imports.py). Importing this name gives that very module, so older imports and patches of it still work."""

import sys

from engine.loops import cuda_listmodes as _module

sys.modules[__name__] = _module
