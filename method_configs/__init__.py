"""nerfstudio method specifications of nerfuser_ns (installed as ``nerfuser_ns.method_configs``).

nerfstudio imports these through the ``nerfstudio.method_configs`` entry points whenever one of its commands
starts, which is also where the offline/CPU runtime fixes get installed for ``ns-train``/``ns-render``/...
"""

from nerfuser_ns import runtime

runtime.install()
