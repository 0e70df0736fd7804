"""The scanner and the comparison of a scan of the phantom with the model."""
