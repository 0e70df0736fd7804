"""The finite-element method: the phantom's model, its element kernels, the linear solvers and path following."""
