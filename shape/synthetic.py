"""A synthetic population of prostates, written as NIfTI in the pelvic MRI dataset's own layout.

Each case is the phantom's parametric body (:func:`phantom.model.mesh.shape.inside_body`, the 26.3 ml rest
shape) under a random map: an overall size, stretches along the anteroposterior (y) and proximodistal (z) axes,
a lobe asymmetry (one side larger than the other), and a smooth random deformation of about a millimetre. The
scale factors are log-normal about 1 and the deformation has zero mean, so the body itself is the population's
known mean shape. Around the prostate (transition zone 4, central gland 5) the label map holds a bladder (1),
the rectum (6) and seminal vesicles (7), so that label selection matters.

Each case is imaged the way one of seven institutions would: its own voxel spacing (0.5 to 0.8 mm in plane,
2.2 to 3.6 mm between slices) and orientation (LPS- or RAS-ordered, an oblique and a sagittal acquisition), so
that a loader must read spacing and orientation from the affine. Files::

    OUT/institution.txt           "<case id> <institution 1-7>" per line
    OUT/data/<case id>_img.nii    a T2-like image (int16), unless images=False
    OUT/data/<case id>_mask.nii   the label map (uint8)
    OUT/synthetic.json            the generator's settings and each case's parameters (not in the real dataset)
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.model.mesh.shape import inside_body
from phantom.shape.dataset import IMAGE_SUFFIX, MASK_SUFFIX
from phantom.shape.errors import ShapeError
from phantom.shape.voxels import RAS_FROM_PHANTOM

#: Field of view of each synthetic image (mm): x, y in plane, z along the body.
FIELD_OF_VIEW_MM = (72.0, 72.0, 84.0)
#: Label numbers the generator writes (the dataset's numbering).
BLADDER, TRANSITION_ZONE, CENTRAL_GLAND, RECTUM, SEMINAL_VESICLES = 1, 4, 5, 6, 7
#: T2-like intensity of each label (background 0 maps to fat and muscle).
INTENSITY = {0: 120.0, BLADDER: 900.0, TRANSITION_ZONE: 260.0, CENTRAL_GLAND: 330.0, RECTUM: 160.0,
             SEMINAL_VESICLES: 700.0}


@dataclass(frozen=True)
class PopulationSpec:
    """How the synthetic shapes vary (standard deviations of the logs of the scale factors, and mm).

    ``mirror_pairs`` makes every second case the mirror image (x -> -x) of the one before, so that the
    population is exactly symmetric about the mid-sagittal plane.
    """

    size_sd: float = 0.10
    anteroposterior_sd: float = 0.08
    proximodistal_sd: float = 0.08
    lobe_asymmetry_sd: float = 0.06
    deformation_mm: float = 1.0
    mirror_pairs: bool = False


@dataclass(frozen=True)
class Acquisition:
    """One institution's voxel spacing (mm, along the image's axes) and direction cosines (columns: RAS)."""

    spacing_mm: tuple[float, float, float]
    directions: tuple[tuple[float, ...], ...]


def _rotation(axis: int, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    i, j = [k for k in range(3) if k != axis]
    rotation = np.eye(3)
    rotation[i, i], rotation[i, j], rotation[j, i], rotation[j, j] = c, -s, s, c
    return rotation


def _directions(matrix: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in matrix)


_LPS = np.diag([-1.0, -1.0, 1.0])
#: The seven institutions' acquisitions.
ACQUISITIONS: tuple[Acquisition, ...] = (
    Acquisition((0.75, 0.75, 2.5), _directions(_LPS)),
    Acquisition((0.6, 0.6, 3.0), _directions(_LPS)),
    Acquisition((0.5, 0.5, 3.6), _directions(_LPS)),
    Acquisition((0.8, 0.8, 2.2), _directions(np.eye(3))),
    Acquisition((0.7, 0.7, 3.0), _directions(_rotation(0, 12.0) @ _LPS)),
    # sagittal: the image's axes run anterior-posterior, inferior-superior and right-left
    Acquisition((0.75, 0.75, 2.5), _directions(np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))),
    Acquisition((0.6, 0.6, 2.7), _directions(_rotation(2, 8.0) @ _LPS)),
)


@dataclass(frozen=True)
class CaseParameters:
    """The random map of one case (see the module docstring); ``mirrored`` flips x after it."""

    size: float
    anteroposterior: float
    proximodistal: float
    lobe_asymmetry: float
    wave_vectors_per_mm: tuple[tuple[float, ...], ...]
    wave_phases: tuple[float, ...]
    wave_amplitudes_mm: tuple[tuple[float, ...], ...]
    mirrored: bool = False

    def reference_points(self, points_mm: np.ndarray) -> np.ndarray:
        """Where points of this case (phantom frame, mm) come from in the reference body."""
        p = points_mm * RAS_FROM_PHANTOM if self.mirrored else points_mm
        waves = np.sin(p @ np.asarray(self.wave_vectors_per_mm).T + np.asarray(self.wave_phases))
        p = p - waves @ np.asarray(self.wave_amplitudes_mm)
        x = p[:, 0] / (1.0 + self.lobe_asymmetry * np.tanh(p[:, 0] / 6.0))
        scales = self.size * np.array([1.0, self.anteroposterior, self.proximodistal])
        return np.column_stack([x, p[:, 1], p[:, 2]]) / scales

    def inside(self, points_mm: np.ndarray) -> np.ndarray:
        """Whether each point (phantom frame, mm) lies inside this case's prostate."""
        return inside_body(self.reference_points(points_mm))


def draw_case(spec: PopulationSpec, rng: np.random.Generator, modes: int = 6,
              wavelength_mm: float = 30.0) -> CaseParameters:
    """One case's random map."""
    directions = rng.normal(size=(modes, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    wave_vectors = directions * (2.0 * math.pi / wavelength_mm) * rng.uniform(0.7, 1.3, (modes, 1))
    amplitudes = rng.normal(size=(modes, 3)) * spec.deformation_mm / math.sqrt(modes)
    return CaseParameters(
        size=float(math.exp(rng.normal(0.0, spec.size_sd))),
        anteroposterior=float(math.exp(rng.normal(0.0, spec.anteroposterior_sd))),
        proximodistal=float(math.exp(rng.normal(0.0, spec.proximodistal_sd))),
        lobe_asymmetry=float(rng.normal(0.0, spec.lobe_asymmetry_sd)),
        wave_vectors_per_mm=tuple(tuple(float(v) for v in row) for row in wave_vectors),
        wave_phases=tuple(float(v) for v in rng.uniform(0.0, 2.0 * math.pi, modes)),
        wave_amplitudes_mm=tuple(tuple(float(v) for v in row) for row in amplitudes))


def label_map(case: CaseParameters, points_mm: np.ndarray) -> np.ndarray:
    """The labels (dataset numbering) at points in the phantom's frame (mm), the prostate centred near 0."""
    labels = np.zeros(len(points_mm), np.uint8)
    x, y, z = points_mm.T
    half_ap_mm = 14.3 * case.size * case.anteroposterior
    top_mm = 20.0 * case.size * case.proximodistal
    bladder = ((x / 24.0) ** 2 + ((y - 4.0) / 18.0) ** 2 + ((z - top_mm - 12.0) / 15.0) ** 2) < 1.0
    rectum = ((x / 13.0) ** 2 + ((y + half_ap_mm + 10.0) / 9.0) ** 2 < 1.0) & (z > -40.0) & (z < 30.0)
    vesicles = (((np.abs(x) - 13.0) / 10.0) ** 2 + ((y + half_ap_mm - 2.0) / 4.0) ** 2
                + ((z - top_mm + 2.0) / 5.0) ** 2) < 1.0
    labels[bladder] = BLADDER
    labels[rectum] = RECTUM
    labels[vesicles] = SEMINAL_VESICLES
    prostate = case.inside(points_mm)
    reference = case.reference_points(points_mm)
    transition = inside_body((reference - np.array([0.0, 2.0, 4.0])) / 0.6)
    labels[prostate] = CENTRAL_GLAND
    labels[prostate & transition] = TRANSITION_ZONE
    return labels


def case_affine(acquisition: Acquisition, centre_ras_mm: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int]]:
    """The image's affine (voxel index -> RAS mm) and shape for a field of view centred at ``centre_ras_mm``."""
    directions = np.asarray(acquisition.directions)
    spacing = np.asarray(acquisition.spacing_mm)
    # the field of view's extent along each image axis: the world box seen along that axis
    extent_mm = np.abs(directions.T) @ np.asarray(FIELD_OF_VIEW_MM)
    shape = tuple(int(n) for n in np.ceil(extent_mm / spacing))
    linear = directions @ np.diag(spacing)
    affine = np.eye(4)
    affine[:3, :3] = linear
    affine[:3, 3] = centre_ras_mm - linear @ ((np.asarray(shape) - 1) / 2.0)
    return affine, shape  # type: ignore[return-value]


def synthesize(out: str | Path, cases: int = 120, seed: int = 0, spec: PopulationSpec | None = None,
               images: bool = True, progress: Callable[[int, int], None] | None = None) -> Path:
    """Write a synthetic population of ``cases`` prostates under ``out`` (see the module docstring);
    ``progress(done, cases)`` is called after each case."""
    with require_extra("shape"):
        import nibabel
    spec = spec or PopulationSpec()
    if cases < 1:
        raise ShapeError(f"--cases must be at least 1, got {cases}")
    out = Path(out)
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    records = []
    lines = []
    case = None
    for number in range(cases):
        rng = np.random.default_rng([seed, number])
        if spec.mirror_pairs and number % 2 == 1 and case is not None:
            case = dataclasses.replace(case, mirrored=not case.mirrored)
        else:
            case = draw_case(spec, rng)
        institution = number % len(ACQUISITIONS)
        prostate_ras_mm = np.array([rng.uniform(-15, 15), rng.uniform(-45, -25), rng.uniform(-70, -50)])
        affine, shape = case_affine(ACQUISITIONS[institution], prostate_ras_mm + rng.uniform(-6, 6, 3))
        index = np.indices(shape).reshape(3, -1).T.astype(float)
        world = index @ affine[:3, :3].T + affine[:3, 3]
        labels = label_map(case, (world - prostate_ras_mm) * RAS_FROM_PHANTOM).reshape(shape)
        uid = f"{number:06d}"
        _write_nifti(nibabel, data / f"{uid}{MASK_SUFFIX}.nii", labels, affine)
        if images:
            lookup = np.zeros(256)
            lookup[list(INTENSITY)] = list(INTENSITY.values())
            intensity = lookup[labels] + rng.normal(0.0, 25.0, shape)
            _write_nifti(nibabel, data / f"{uid}{IMAGE_SUFFIX}.nii", np.clip(intensity, 0, None).astype(np.int16),
                         affine)
        lines.append(f"{uid} {institution + 1}")
        records.append({"case": uid, "institution": institution + 1, **dataclasses.asdict(case)})
        if progress is not None:
            progress(number + 1, cases)
    (out / "institution.txt").write_text("\n".join(lines) + "\n")
    settings = {"seed": seed, "cases": cases, "spec": dataclasses.asdict(spec), "mean_shape": "the phantom's "
                "parametric body (phantom.model.mesh.shape.inside_body)", "records": records}
    (out / "synthetic.json").write_text(json.dumps(settings, indent=1))
    return out


def _write_nifti(nibabel: Any, path: Path, values: np.ndarray, affine: np.ndarray) -> None:
    image = nibabel.Nifti1Image(values, affine)
    image.set_qform(affine, code=1)
    image.set_sform(affine, code=1)
    nibabel.save(image, str(path))
