"""Rail: train-run batches (calibration, track quality, the bridge reading from bogie APs)."""
