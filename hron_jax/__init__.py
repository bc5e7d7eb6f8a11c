"""hron-jax: hierarchical relational object navigation, end to end in JAX on MuJoCo MJX."""

__version__ = "0.1.0"
