"""Independent pieces of work across processes and machines on Ray (the optional ``scale`` extra).

``map_variants(fn, items, ray="local")`` runs ``fn`` on every item on warm Ray workers (actors
that keep their Warp kernels loaded), retrying the items of a worker that dies; ``ray="off"`` runs
them in this process. ``WarmStates(build, items, ray=...)`` keeps one state per item (a model and
its kernels) on the workers and calls functions of them, all items at once, as often as needed.
See :mod:`dmarionette.scale.ray_map`, :mod:`dmarionette.scale.warm_states` and docs/sweep.md.
"""

from .ray_map import WorkerLostError as WorkerLostError
from .ray_map import check_ray_address as check_ray_address
from .ray_map import connect_ray as connect_ray
from .ray_map import default_ray_mode as default_ray_mode
from .ray_map import imap_variants as imap_variants
from .ray_map import map_variants as map_variants
from .ray_map import ray_available as ray_available
from .ray_map import ray_mode as ray_mode
from .ray_map import shutdown_ray as shutdown_ray
from .ray_map import start_local_ray as start_local_ray
from .warm_states import WarmStates as WarmStates

__all__ = ["WarmStates", "WorkerLostError", "check_ray_address", "connect_ray", "default_ray_mode", "imap_variants",
           "map_variants", "ray_available", "ray_mode", "shutdown_ray", "start_local_ray"]
