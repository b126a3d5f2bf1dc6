"""Deprecated alias of drvs.core.model (the layers as folders, docs/architecture.md).

drvs.model moved to drvs.core.model; this alias goes in the next release."""

# drvs-layers-shim: a deprecated alias, not rewritten by scripts/migrate_layers.py
import sys
import warnings
from typing import TYPE_CHECKING

from drvs.core import model as _new

if TYPE_CHECKING:
    from drvs.core.model import *  # noqa: F403

warnings.warn("drvs.model is deprecated: import drvs.core.model", DeprecationWarning, stacklevel=2)
# `import drvs.model` and `from drvs.model import X` get the new module itself.
sys.modules[__name__] = _new
