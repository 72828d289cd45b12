"""One error hierarchy for the product; messages name the input and what is wrong."""


class MdssError(Exception):
    """Base class of every error mdss_ros raises on purpose."""


class MeshError(MdssError):
    """A mesh is unusable (empty, degenerate, inverted, non-manifold, unreadable)."""


class SceneError(MdssError):
    """A scene file or override is invalid; the message names file, key and problem."""


class ReportError(RuntimeError):
    """A study or probe could not produce its numbers (e.g. a static solve did not
    converge, or a run went non-finite). Reports mark the row failed and go on."""


class CacheError(MdssError):
    """A precompute cache file is corrupt or was written for other inputs."""
