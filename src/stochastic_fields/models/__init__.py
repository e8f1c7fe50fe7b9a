"""Trainable models behind one protocol (``RadianceModel``): S-NeRF and the baselines."""
