"""Nerfstudio ``MethodSpecification``s registered by gsticker's entry points.

Importing this package applies the plugin's host fixes (offline LPIPS, torch >= 2.6 checkpoint types),
because Nerfstudio imports every registered entry point before it builds or loads any model.
"""

from gsticker_plugin import compat as _compat

_compat.apply()
