"""ccrjax: Collective Conditioned Reflex for multi-robot teams, in JAX."""

__version__ = "0.1.0"
