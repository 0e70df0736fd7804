"""The fidelity levels of the volume estimate, cheapest first, and the response table."""
