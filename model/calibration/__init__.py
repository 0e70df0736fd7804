"""Calibration of the model to measured volumes: sweeps of forward solves (Dask) and the fit."""
