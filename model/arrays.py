"""The array types of the model's signatures (and of the parts that use its arrays): numpy arrays of one dtype.

Shapes and units are in each function's docstring; these only say the dtype, which mypy checks.
"""

import numpy as np
import numpy.typing as npt

#: Positions, volumes, pressures, forces, matrix entries: float64.
FloatArray = npt.NDArray[np.float64]
#: Node and element indices (tetrahedra, triangles, dofs): int64.
IntArray = npt.NDArray[np.int64]
#: A CSR matrix's column indices, stored as int32 (half the memory of a factor on disk).
Int32Array = npt.NDArray[np.int32]
#: Masks.
BoolArray = npt.NDArray[np.bool_]
