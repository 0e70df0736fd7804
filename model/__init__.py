"""The finite-element model of the phantom and its inverse problem (SI units inside: m, Pa, m^3, N)."""
