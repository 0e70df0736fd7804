"""The array types of the model's signatures (and of the parts that use its arrays): numpy arrays of one dtype.

Shapes and units are in each function's docstring; these only say the dtype, which mypy checks.
"""

import numpy as np
import numpy.typing as npt

#: Positions, volumes, pressures, forces, matrix entries: float64.
FloatArray = npt.NDArray[np.float64]
#: Node and element indices (tetrahedra, triangles, dofs): int64 (a CSR's column indices may be int32).
IntArray = npt.NDArray[np.int64]
#: Masks.
BoolArray = npt.NDArray[np.bool_]
