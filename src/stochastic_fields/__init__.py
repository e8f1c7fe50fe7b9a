"""stochastic-fields: Stochastic Neural Radiance Fields with calibrated colour and depth uncertainty."""

__version__ = "0.1.0"
