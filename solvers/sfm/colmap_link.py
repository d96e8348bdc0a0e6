"""pycolmap, COLMAP's official bindings, imported where a step calls it.

Everything of mpe3d that calls COLMAP gets it from :func:`require_pycolmap`:
one line when it is missing, and COLMAP's log silenced (a failure is said in
mpe3d's own one line, not in glog's).
"""

from __future__ import annotations

from mpe3d.errors import MpeError


def require_pycolmap():
    """pycolmap, or one line saying how to get it."""
    try:
        import pycolmap
    except ImportError:
        raise MpeError("COLMAP support needs pycolmap: pip install pycolmap") from None
    logging = getattr(pycolmap, "logging", None)
    if logging is not None and hasattr(logging, "minloglevel"):
        logging.minloglevel = 3  # none: a failure is said in our one line
    return pycolmap
