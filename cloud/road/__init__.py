"""Road: the fused profile (GMRF with drift and long-wave nuisances), pass alignment, vehicle calibration."""
