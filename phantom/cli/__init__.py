"""Every command line of ``phantom``: the only code that joins the model, the scan, the host and the HIL."""
