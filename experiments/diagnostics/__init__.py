"""Diagnostics: the surrogate's reward terms, IK local minima, float32 precision across CPUs."""
