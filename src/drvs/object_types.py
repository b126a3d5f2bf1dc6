"""Deprecated alias of drvs.core.object_types (the layers as folders, docs/architecture.md).

drvs.object_types moved to drvs.core.object_types; this alias goes in the next release."""

# drvs-layers-shim: a deprecated alias, not rewritten by scripts/migrate_layers.py
import sys
import warnings
from typing import TYPE_CHECKING

from drvs.core import object_types as _new

if TYPE_CHECKING:
    from drvs.core.object_types import *  # noqa: F403

warnings.warn("drvs.object_types is deprecated: import drvs.core.object_types", DeprecationWarning, stacklevel=2)
# `import drvs.object_types` and `from drvs.object_types import X` get the new module itself.
sys.modules[__name__] = _new
