"""Ray, the optional ``cluster`` extra: the one install message, and a session that starts a local Ray
(or joins ``address``) only when there is work and stops only what it started
(``langfield sweep``, ``langfield preprocess --address``; docs/cluster.md)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

INSTALL_HINT = "Ray is not installed: pip install 'langfield[cluster]' (or pip install -e '.[cluster]')"


def require_ray():
    """The ray module, or a RuntimeError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise RuntimeError(INSTALL_HINT) from None
    return ray


@contextmanager
def ray_session(address: str | None, needed: bool = True) -> Iterator:
    """Yields the ray module, initialised when ``needed``: a local Ray in the process for no
    ``address``, else the cluster at ``address`` (``auto``, ``ray://host:10001``). A Ray this session
    started is shut down on exit; one already running is left as it was."""
    ray = require_ray()
    started = needed and not ray.is_initialized()
    if started:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()
