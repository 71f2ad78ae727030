"""The formats on disk: plan, dataset, observations, result document, calibration export; their schemas."""
