"""ccrjax: Collective Conditioned Reflex for multi-robot teams, in JAX."""

__version__ = "0.1.0"


def __getattr__(name: str):
    """``ccrjax.load_policy`` and ``ccrjax.load_team``, imported on first use so that
    ``import ccrjax`` stays light."""
    if name in ("load_policy", "load_team"):
        from ccrjax.run import policy

        return getattr(policy, name)
    raise AttributeError(f"module 'ccrjax' has no attribute {name!r}")
