"""hammer: a central agent that learns to message many lightweight local RL agents (HAMMER)."""

__version__ = "0.1.0"
