"""The analyses of a trained run: encode shapes, decode latent vectors, the average shape and the clusters.

Latent vectors are the encoder's means (no sampling). A decoded shape is the 0.5 level of the decoder's voxel
probabilities, surfaced by marching cubes; its volume (ml) comes from the run's voxel size. Surfaces returned
here are in the phantom's frame (x to the patient's left, y anterior, z toward the base), in mm, centred on
the shape's grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.model.fidelity.table_files import Member, read_members
from phantom.model.shape_file import GLAND_VOLUME_RANGE_ML
from phantom.shape import vae as network
from phantom.shape.checkpoint import read_run
from phantom.shape.dataset import PROSTATE_LABELS, find_cases, read_shape, shape_grid
from phantom.shape.errors import ShapeError
from phantom.shape.vae import Parameters, VAEConfig
from phantom.shape.voxels import ClosedSurface, LabelMask, surface_of

with require_extra("shape"):
    import jax

#: Shapes encoded or decoded per call of the jitted network (a fixed size, so it compiles once).
CHUNK = 16


@dataclass
class DecodedShape:
    """A decoded shape: its latent vector, voxel probabilities ``(G, G, G)``, surface (phantom frame, mm) and
    volume (ml, of the surface)."""

    latent: np.ndarray
    probabilities: np.ndarray
    vertices_mm: np.ndarray
    triangles: np.ndarray
    volume_ml: float

    def write(self, path: str | Path) -> Path:
        """Write the surface as .obj, .ply or .stl (by the extension), in mm."""
        return write_surface(self.vertices_mm, self.triangles, path)


def write_surface(vertices_mm: np.ndarray, triangles: np.ndarray, path: str | Path) -> Path:
    """A triangle surface (mm) written as .obj, .ply or .stl."""
    # trimesh (0.3 s to import) only where a mesh is written
    with require_extra("shape"):
        import trimesh

    path = Path(path)
    if path.suffix.lower() not in (".obj", ".ply", ".stl"):
        raise ShapeError(f"{path}: write the mesh as .obj, .ply or .stl")
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(vertices_mm, triangles, process=False).export(str(path))
    return path


class ShapeModel:
    """A trained run, loaded: its network, the grid it works on, and the latent vectors of its cases."""

    def __init__(self, run: Path, config: dict[str, Any], params: Parameters, statistics: Parameters):
        self.run = run
        self.config = config
        self.vae = VAEConfig.from_dict(config["vae"])
        self.voxel_mm = float(config["data"]["voxel_mm"])
        self.grid_size = int(config["data"]["grid_size"])
        self.labels = tuple(config["data"].get("labels", PROSTATE_LABELS))
        self.params, self.statistics = params, statistics
        vae = self.vae
        self._encode = jax.jit(lambda p, s, x: network.encode(p, s, vae, x)[:2])
        self._decode = jax.jit(lambda p, s, z: jax.nn.sigmoid(network.decode_logits(p, s, vae, z)[0]))

    @classmethod
    def load(cls, run: str | Path) -> ShapeModel:
        """Load a run folder written by :func:`phantom.shape.training.train`."""
        return cls(Path(run), *read_run(run))

    def encode_grids(self, occupancy: np.ndarray) -> np.ndarray:
        """Latent means ``(N, latent_dim)`` of shape grids ``(N, G, G, G)``."""
        return self.encode_distributions(occupancy)[0]

    def encode_distributions(self, occupancy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Latent means and log-variances ``(N, latent_dim)`` of shape grids ``(N, G, G, G)``."""
        occupancy = np.asarray(occupancy, np.float32)
        if occupancy.ndim != 4 or occupancy.shape[1:] != (self.grid_size,) * 3:
            raise ShapeError(f"expected grids of {self.grid_size}^3 voxels, got shape {occupancy.shape[1:]}")
        means, log_variances = [], []
        for start in range(0, len(occupancy), CHUNK):
            chunk = occupancy[start:start + CHUNK]
            padded = np.concatenate([chunk, np.zeros((CHUNK - len(chunk), *chunk.shape[1:]), np.float32)])
            mean, log_variance = self._encode(self.params, self.statistics, padded)
            means.append(np.asarray(mean)[:len(chunk)])
            log_variances.append(np.asarray(log_variance)[:len(chunk)])
        return np.concatenate(means).astype(np.float64), np.concatenate(log_variances).astype(np.float64)

    def decode_grids(self, latents: np.ndarray) -> np.ndarray:
        """Voxel probabilities ``(N, G, G, G)`` of latent vectors ``(N, latent_dim)``."""
        latents = np.atleast_2d(np.asarray(latents, np.float32))
        if latents.shape[1] != self.vae.latent_dim:
            raise ShapeError(f"latent vectors must have {self.vae.latent_dim} values, got {latents.shape[1]}")
        grids = []
        for start in range(0, len(latents), CHUNK):
            chunk = latents[start:start + CHUNK]
            padded = np.concatenate([chunk, np.zeros((CHUNK - len(chunk), chunk.shape[1]), np.float32)])
            grids.append(np.asarray(self._decode(self.params, self.statistics, padded))[:len(chunk)])
        return np.concatenate(grids)

    def decode(self, latent: np.ndarray) -> DecodedShape:
        """One latent vector decoded and surfaced (see the module docstring)."""
        probabilities = self.decode_grids(latent)[0]
        surface = surface_of(probabilities, self.voxel_mm).mirrored_x()
        return DecodedShape(np.asarray(latent, float), probabilities, surface.vertices_mm, surface.triangles,
                            surface.volume_ml())

    def grid_of(self, shape: LabelMask | ClosedSurface, name: str) -> np.ndarray:
        """A shape on this run's grid (its voxel size), centred on its centroid; ShapeError for a shape of no
        gland's size (:data:`~phantom.model.shape_file.GLAND_VOLUME_RANGE_ML`, the bound the shape inverse's
        targets keep)."""
        volume_ml = shape.volume_ml()
        low, high = GLAND_VOLUME_RANGE_ML
        if not low <= volume_ml <= high:
            # a speck of a mask still lands on a voxel or two of the grid, and the encoder gave it a latent vector
            # as if it were a gland
            try:
                trained_ml = self.trained_volumes_ml()
                trained = f"; this run was trained on {trained_ml.min():.1f}-{trained_ml.max():.1f} ml"
            except ShapeError:  # a run without its cases' volumes: the bound alone
                trained = ""
            raise ShapeError(f"{name}: the shape is {volume_ml:.3g} ml, no gland's size ({low:g}-{high:g} ml)"
                             f"{trained}: give a whole gland's mask (its voxel sizes in the header) or a closed mesh "
                             "in mm")
        return shape_grid(shape, self.voxel_mm, self.grid_size, name)

    def read(self, path: str | Path) -> LabelMask | ClosedSurface:
        """One shape file (mask, label map with this run's labels, or closed mesh in the phantom's frame)."""
        cases = find_cases(path)
        if len(cases) != 1:
            raise ShapeError(f"{path} holds {len(cases)} shapes: give one file")
        return read_shape(cases[0], self.labels)

    def encode_shape(self, shape: LabelMask | ClosedSurface, name: str) -> np.ndarray:
        """The latent vector of one shape."""
        latent: np.ndarray = self.encode_grids(self.grid_of(shape, name)[None])[0]
        return latent

    def encode_file(self, path: str | Path) -> np.ndarray:
        """The latent vector of one shape file."""
        return self.encode_shape(self.read(path), str(path))

    def case_latents(self) -> tuple[list[str], np.ndarray]:
        """The names and latent means of the run's cases (from ``latents.npz``)."""
        path = self.run / "latents.npz"
        if not path.is_file():
            raise ShapeError(f"{self.run}: no latents.npz (the run did not finish): train it again")
        stored = read_members(path, {"names": Member((None,), "U"), "mean": Member((None, self.vae.latent_dim))},
                              f"the latents {path}", "train the run again (phantom shape train)", ShapeError)
        if len(stored["names"]) != len(stored["mean"]):
            raise ShapeError(f"the latents {path} name {len(stored['names'])} cases for {len(stored['mean'])} "
                             f"latent vectors: train the run again (phantom shape train)")
        return [str(name) for name in stored["names"]], np.asarray(stored["mean"], float)

    def trained_volumes_ml(self) -> np.ndarray:
        """The volumes (ml) of the cases the run was trained on, as read (from ``latents.npz``)."""
        path = self.run / "latents.npz"
        stored = read_members(path, {"volumes_ml": Member((None,))}, f"the latents {path}",
                              "train the run again (phantom shape train)", ShapeError)
        if not len(stored["volumes_ml"]):
            raise ShapeError(f"the latents {path} hold no volumes: train the run again (phantom shape train)")
        return np.asarray(stored["volumes_ml"], float)

    def average(self) -> DecodedShape:
        """The average shape: the mean of every case's latent vector, decoded (the paper's average prostate)."""
        _, latents = self.case_latents()
        return self.decode(latents.mean(axis=0))

    def clusters(self, k: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[DecodedShape]]:
        """k-means of the cases' latent vectors: (centres ``(k, L)``, each case's cluster, decoded centres).

        Clusters are numbered by size, largest first.
        """
        # scipy's submodules load on first use
        from scipy.cluster.vq import kmeans2

        _, latents = self.case_latents()
        if not 1 <= k <= len(latents):
            raise ShapeError(f"--k must be between 1 and the run's {len(latents)} cases, got {k}")
        centres, assignment = kmeans2(latents, k, minit="++", seed=seed)
        sizes = np.bincount(assignment, minlength=k)
        order = np.argsort(-sizes, kind="stable")
        renumber = np.empty(k, int)
        renumber[order] = np.arange(k)
        centres = centres[order]
        return centres, renumber[assignment], [self.decode(centre) for centre in centres]
