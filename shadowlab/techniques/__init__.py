"""Real-time shadow techniques, one module per family, registered by name.

``registry`` is :mod:`shadowlab.techniques.base`: ``registry.get("pcf")``, ``registry.names()``.
Technique modules are imported on first use of the registry, not here, so importing this
package needs no Mitsuba variant.
"""

from . import base as registry
from .base import (Param, ShadowResult, Technique, get, names, param_table_markdown, parse_sets,
                   register)

__all__ = ["registry", "Param", "ShadowResult", "Technique", "get", "names", "param_table_markdown",
           "parse_sets", "register"]
