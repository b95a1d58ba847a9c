"""flowmaps-jax: FlowMaps (flow matching over future object boxes) and FlowSim, in JAX/Flax."""

__version__ = "0.1.0"
