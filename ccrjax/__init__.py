"""ccrjax: Collective Conditioned Reflex for multi-robot teams, in JAX."""

__version__ = "0.1.0"


def __getattr__(name: str):
    """``ccrjax.load_policy``, imported on first use so that ``import ccrjax`` stays light."""
    if name == "load_policy":
        from ccrjax.run.policy import load_policy

        return load_policy
    raise AttributeError(f"module 'ccrjax' has no attribute {name!r}")
