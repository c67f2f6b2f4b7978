"""Speckle-tracking baselines beside PWF: UMPA, LCS, GF and MIST (tracking; Table S1 of the paper)."""
