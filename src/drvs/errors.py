"""Deprecated alias of drvs.core.errors (the layers as folders, docs/architecture.md).

drvs.errors moved to drvs.core.errors; this alias goes in the next release."""

# drvs-layers-shim: a deprecated alias, not rewritten by scripts/migrate_layers.py
import sys
import warnings
from typing import TYPE_CHECKING

from drvs.core import errors as _new

if TYPE_CHECKING:
    from drvs.core.errors import *  # noqa: F403

warnings.warn("drvs.errors is deprecated: import drvs.core.errors", DeprecationWarning, stacklevel=2)
# `import drvs.errors` and `from drvs.errors import X` get the new module itself.
sys.modules[__name__] = _new
