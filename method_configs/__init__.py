"""Nerfstudio ``MethodSpecification``s registered by gsticker's entry points (``nerfstudio.method_configs``)."""
