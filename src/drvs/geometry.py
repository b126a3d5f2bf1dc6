"""Deprecated alias of drvs.core.geometry (the layers as folders, docs/architecture.md).

drvs.geometry moved to drvs.core.geometry; this alias goes in the next release."""

# drvs-layers-shim: a deprecated alias, not rewritten by scripts/migrate_layers.py
import sys
import warnings
from typing import TYPE_CHECKING

from drvs.core import geometry as _new

if TYPE_CHECKING:
    from drvs.core.geometry import *  # noqa: F403

warnings.warn("drvs.geometry is deprecated: import drvs.core.geometry", DeprecationWarning, stacklevel=2)
# `import drvs.geometry` and `from drvs.geometry import X` get the new module itself.
sys.modules[__name__] = _new
