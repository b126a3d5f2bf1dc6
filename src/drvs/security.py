"""Deprecated alias of drvs.wire.security (the layers as folders, docs/architecture.md).

drvs.security moved to drvs.wire.security; this alias goes in the next release."""

# drvs-layers-shim: a deprecated alias, not rewritten by scripts/migrate_layers.py
import sys
import warnings
from typing import TYPE_CHECKING

from drvs.wire import security as _new

if TYPE_CHECKING:
    from drvs.wire.security import *  # noqa: F403

warnings.warn("drvs.security is deprecated: import drvs.wire.security", DeprecationWarning, stacklevel=2)
# `import drvs.security` and `from drvs.security import X` get the new module itself.
sys.modules[__name__] = _new
