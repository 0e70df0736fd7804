"""Scene files (TOML): which phantom, which material, what to compute (architecture.md, "The scene file").

A scene is parsed once, here, into types: the phantom (mesh, units, chambers and their labels, fixed group), the
built-in prostate's ``[geometry]``, the ``[material]``, the ``[model]`` settings (:class:`ModelSettings`) and the
``[outputs]``; anything missing or out of range is a SceneError naming the key and the file. Other parts read
these fields; the parsed TOML (``Scene.raw``) is kept only to write a scene back out (a calibrated scene, the
simulated board's truth) and for the tables other parts own (``[[steps]]``, ``[host]``).
"""

import copy
import dataclasses
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from phantom import is_finite_number, read_text
from phantom.model.errors import SceneError, check_known_keys, setting_refused
from phantom.model.mesh.geometry import ProstateGeometry, geometry_from_table

#: The largest scene file read (bytes): a scene of the most steps a timeline may have is about 100 KiB.
MAX_SCENE_BYTES = 2**20

#: Names of the shipped scenes, as accepted by :func:`load_scene`.
#: "builtin" and "builtin:prostate" are the physical model (Ecoflex modulus, co-rotational) the FEM tests use;
#: "builtin:converged" is the calibration to the measurements (Gent material) on 10-node, nearly incompressible
#: elements on a mesh converged to under 1 %, the daemon's default (seconds to a minute a full solve; its table's
#: volumes and its surface's shapes ship with it); "builtin:calibrated" is the earlier fit on 4-node,
#: compressible elements on a coarse 4 mm mesh (fast, but 7-39 % from its own converged growth, bench/README.md).
#: The folder of the built-in scenes and the table files they ship.
SCENES_DIR = Path(__file__).resolve().parent / "scenes"
BUILTIN_SCENES = {"builtin": "prostate.toml", "builtin:prostate": "prostate.toml",
                  "builtin:calibrated": "prostate_calibrated.toml", "builtin:converged": "prostate_converged.toml"}

#: The Yeoh law's coefficients in a scene's [material]: C20 and C30 as multiples of C10 = mu/2 (dimensionless).
YEOH_KEYS = ("yeoh_c20_over_c10", "yeoh_c30_over_c10")
#: The keys each table of a scene may hold; any other is refused with the nearest known key (a misspelt key would
#: otherwise be ignored and its default used in silence). ``[geometry]``'s are ProstateGeometry's fields.
PHANTOM_KEYS = ("mesh", "units", "chambers", "chamber_labels", "fixed")
MATERIAL_KEYS = ("model", "youngs_modulus_kpa", "poisson_ratio", "gent_jm", *YEOH_KEYS)
MODEL_KEYS = ("fidelity", "accuracy_pct", "pressure_max_kpa", "table_points", "table_volumes", "table_shapes")
LOAD_KEYS = ("density_kg_m3", "gravity_m_s2")
OUTPUT_KEYS = ("volumes", "shape")
#: The tables of a scene this module reads, and those the host reads and checks itself (the timeline).
MODEL_SECTIONS = ("phantom", "geometry", "material", "model", "load", "outputs")
HOST_SECTIONS = ("steps", "timeline", "host")

#: The surface groups of the built-in prostate's mesh (phantom.model.mesh.prostate.tag_surfaces): the chamber walls
#: a scene may name in ``[phantom] chambers``, and the fixation patch, the only group its ``fixed`` may name.
BUILTIN_CHAMBER_GROUPS = ("chamber0", "chamber1", "chamber2")
BUILTIN_FIXED_GROUP = "fixed"
#: The range of ``[material] youngs_modulus_kpa`` (kPa): the softest gels and silicones (Ecoflex 00-10 about 50,
#: the calibrated phantom 2.6-11) to the stiffest elastomers with margin either way, 0.1 kPa to 100 MPa. Outside it
#: the number is in another unit or a typo: 1e300 was taken, and the model answered zero growth in silence.
YOUNGS_MODULUS_RANGE_KPA = (0.1, 1.0e5)

#: Length units a scene may declare for its mesh, and their size in metres.
LENGTH_UNITS_M = {"m": 1.0, "cm": 1.0e-2, "mm": 1.0e-3, "um": 1.0e-6}

MATERIAL_MODELS = ("corotational", "linear", "neo_hookean", "gent", "yeoh")
#: The hyperelastic laws (finite strain, an energy that grows without bound as an element collapses).
HYPERELASTIC_MODELS = ("neo_hookean", "gent", "yeoh")

#: The gauge pressure (Pa) the phantom is driven to at most (what its blowers give and the model is trusted
#: for): a scene's default ``[model] pressure_max_kpa``, and the highest pressure a calibration measurement may
#: have.
PRESSURE_LIMIT_PA = 3000.0
#: The pressure sensor's range (kPa): the MPXV7025G reads gauge pressures up to 25 kPa (docs/hardware.md), so a
#: scene's ``[model] pressure_max_kpa`` above it is a pressure no phantom of this rig is driven to, most likely
#: written in Pa (3000 for 3 kPa).
SENSOR_RANGE_KPA = 25.0
#: The ways the model answers "what volumes do these pressures give" (:mod:`phantom.model.fidelity.levels`).
FIDELITY_LEVELS = ("rest", "updated", "full", "table")
#: Volume accuracy assumed when a scene states none (percent of the volume).
DEFAULT_ACCURACY_PCT = 1.0
#: Grid points per pressure axis of a response table: 7^3 = 343 solves (0.5 kPa steps for a 3 kPa limit). On
#: the calibrated model 5 points missed full solves by up to 3.5 % of a chamber's volume (its cavity's curve has
#: an inflection), 7 by 0.1-0.2 % (bench/README.md, "The daemon on the calibrated model").
DEFAULT_TABLE_POINTS = 7
#: The most grid points per pressure axis a scene may ask of its table: 13 halves the default's step (0.25 kPa on
#: 3 kPa), 13^3 = 2197 full solves, at about 3 s of CPU a point on builtin:converged (bench/README.md, "The table's
#: cost per point") about 2 CPU-hours, once per machine. Every shipped scene uses the default 7; 100 asked for
#: 10^6 solves (35 CPU-days, the daemon hung building it).
MAX_TABLE_POINTS = 13
#: Ecoflex 00-10's density (kg/m^3), the default of a scene's ``[load] density_kg_m3``.
SILICONE_DENSITY_KG_M3 = 1040.0
#: Water's density (kg/m^3): a phantom measured in water feels only its density's excess over it.
WATER_DENSITY_KG_M3 = 998.0
#: Standard gravity (m/s^2).
STANDARD_GRAVITY_M_S2 = 9.80665
#: Where a measurement was taken (the measurements CSV's ``medium`` column): hanging in air from the tube
#: junction (the default), or in water.
MEDIA = ("air", "water")
#: How people name the three chambers when the scene says nothing (``[phantom] chamber_labels``).
DEFAULT_CHAMBER_LABELS = ("base", "left lobe", "right lobe")


@dataclass(frozen=True)
class Material:
    """Isotropic elastic material; modulus in Pa.

    ``model``: "linear" (small strain), "corotational" (small strain in a rotated frame), "neo_hookean"
    (``W = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2``) or "gent" (``W = -(mu Jm/2) ln(1 - (I1 - 3)/Jm)
    - mu ln J + lambda/2 (ln J)^2``, defined for I1 - 3 < Jm: the chains lock as I1 - 3 approaches
    ``gent_jm``, dimensionless; Jm -> inf is the Neo-Hookean law) or "yeoh" (``W = C10 (I1 - 3) + C20 (I1 - 3)^2
    + C30 (I1 - 3)^3 - mu ln J + lambda/2 (ln J)^2`` with ``C10 = mu/2``, ``C20 = yeoh_c20_over_c10 C10``,
    ``C30 = yeoh_c30_over_c10 C10``). mu and lambda are the Lame constants of E and nu, so every model has the
    same small-strain stiffness. On 10-node elements the hyperelastic laws take the isochoric ``J^(-2/3) I1`` and
    a volumetric ``K/2 (J - 1)^2`` (:mod:`phantom.model.fem.materials`).
    """

    model: str
    youngs_modulus_pa: float
    poisson_ratio: float
    gent_jm: float | None = None
    yeoh_c20_over_c10: float | None = None
    yeoh_c30_over_c10: float | None = None

    @property
    def lame_mu_pa(self) -> float:
        return self.youngs_modulus_pa / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lame_lambda_pa(self) -> float:
        nu = self.poisson_ratio
        return self.youngs_modulus_pa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def bulk_modulus_pa(self) -> float:
        """``K = E / (3 (1 - 2 nu))``, the modulus of the volumetric energy ``K/2 (J - 1)^2`` of the mixed
        (10-node) formulation; ``K / mu = 2 (1 + nu) / (3 (1 - 2 nu))`` (1000 at nu = 0.4995, 5000 at 0.4999)."""
        return self.youngs_modulus_pa / (3.0 * (1.0 - 2.0 * self.poisson_ratio))


@dataclass(frozen=True)
class ModelSettings:
    """A scene's ``[model]`` table, checked: how the model answers (every key optional).

    fidelity : one of FIDELITY_LEVELS, or None to let the volume estimator pick the cheapest level within
        ``accuracy_pct``; accuracy_pct : the volume accuracy wanted (% of the volume, > 0); pressure_max_pa :
        the highest chamber pressure (Pa; the file's ``pressure_max_kpa``, default PRESSURE_LIMIT_PA);
        table_points : grid points per pressure axis of the ``table`` level (an integer >= 2);
        table_volumes : the file's ``table_volumes``, resolved beside the scene: the ``table`` level's volumes,
        shipped with the scene so that no machine must build them (``phantom.model.fidelity.response_table``
        checks that they belong to this model), or None; table_shapes : likewise the outer surface's shapes
        over the box (on a coarser grid), or None (each shape is then a full solve).
    """

    fidelity: str | None = None
    accuracy_pct: float = DEFAULT_ACCURACY_PCT
    pressure_max_pa: float = PRESSURE_LIMIT_PA
    table_points: int = DEFAULT_TABLE_POINTS
    table_volumes: Path | None = None
    table_shapes: Path | None = None


@dataclass(frozen=True)
class Load:
    """A scene's ``[load]`` table: the silicone's density (kg/m^3) and the gravitational acceleration (m/s^2,
    a vector in the mesh's frame; the built-in prostate hangs from its tube junction at the base, +z, so
    ``[0, 0, -9.81]``). No table: no gravity."""

    density_kg_m3: float = SILICONE_DENSITY_KG_M3
    gravity_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def body_force_n_per_m3(self, medium: str = "air") -> tuple[float, float, float]:
        """The body force per unit volume (N/m^3) hanging in ``medium``: the density times g in air, only the
        density's excess over water's in water (the water's buoyancy; the hydrostatic pressure's gradient on the
        chambers' air is left out)."""
        if medium not in MEDIA:
            raise SceneError(f"unknown medium {medium!r}: a measurement is taken in one of {', '.join(MEDIA)}")
        density = self.density_kg_m3 - (WATER_DENSITY_KG_M3 if medium == "water" else 0.0)
        x, y, z = self.gravity_m_s2
        return (density * x, density * y, density * z)


@dataclass(frozen=True)
class Outputs:
    """What a scene asks the model to compute."""

    volumes: bool = True
    shape: bool = False


@dataclass(frozen=True)
class Scene:
    """A parsed scene.

    Attributes
    ----------
    path : Path or None
        The scene file (None for none).
    mesh : str
        ``"builtin:prostate"`` or an absolute path to a mesh file meshio reads.
    units : str
        Length unit of the mesh file's coordinates (a key of ``LENGTH_UNITS_M``).
    chambers : list of str
        Surface group names of the chamber walls, in chamber order.
    chamber_labels : list of str
        The names people see for the chambers (``[phantom] chamber_labels``, else base, left lobe, right lobe
        for three chambers, else the group names), one per chamber.
    fixed : str or None
        Surface group held by penalty springs; None removes rigid-body motion only.
    material : Material
    outputs : Outputs
    model_settings : ModelSettings
        The ``[model]`` table (defaults when absent).
    load : Load
        The ``[load]`` table: density and gravity (no gravity without one).
    steps : list of dict
        The timeline, raw (read by the host).
    raw : dict
        The whole parsed TOML: for writing a scene back out, and for the tables other parts own.
    geometry : ProstateGeometry or None
        The built-in prostate's chamber sizes and positions and fixation radius (``[geometry]``, defaults
        when absent); None for a mesh file.
    """

    path: Path | None
    mesh: str
    units: str
    chambers: list[str]
    fixed: str | None
    material: Material
    outputs: Outputs
    chamber_labels: list[str] = field(default_factory=list)
    model_settings: ModelSettings = field(default_factory=ModelSettings)
    load: Load = field(default_factory=Load)
    steps: list[dict[str, Any]] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict)
    geometry: ProstateGeometry | None = None

    @property
    def length_scale_m(self) -> float:
        """Metres per mesh-file length unit."""
        return LENGTH_UNITS_M[self.units]


def resolved_scene(scene: Scene) -> list[tuple[str, str, Any, bool]]:
    """Every value of the tables this module reads, as the model uses it, with whether the file gave it (else it
    is the default): ``(section, key, value, from_file)`` in the order of the known keys (``phantom scene check``).
    A key with no typed field here is shown as the file has it."""
    material, settings, load = scene.material, scene.model_settings, scene.load
    typed: dict[str, dict[str, Any]] = {
        "phantom": {"mesh": scene.mesh, "units": scene.units, "chambers": scene.chambers,
                    "chamber_labels": scene.chamber_labels, "fixed": scene.fixed},
        "geometry": dataclasses.asdict(scene.geometry) if scene.geometry is not None else {},
        "material": {"model": material.model, "youngs_modulus_kpa": material.youngs_modulus_pa / 1e3,
                     "poisson_ratio": material.poisson_ratio, "gent_jm": material.gent_jm},
        "model": {"fidelity": settings.fidelity, "accuracy_pct": settings.accuracy_pct,
                  "pressure_max_kpa": settings.pressure_max_pa / 1e3, "table_points": settings.table_points,
                  "table_volumes": settings.table_volumes and str(settings.table_volumes),
                  "table_shapes": settings.table_shapes and str(settings.table_shapes)},
        "load": {"density_kg_m3": load.density_kg_m3, "gravity_m_s2": list(load.gravity_m_s2)},
        "outputs": dataclasses.asdict(scene.outputs),
    }
    known = {"phantom": PHANTOM_KEYS, "geometry": tuple(typed["geometry"]), "material": MATERIAL_KEYS,
             "model": MODEL_KEYS, "load": LOAD_KEYS, "outputs": OUTPUT_KEYS}
    rows = []
    for section in MODEL_SECTIONS:
        given = scene.raw.get(section, {})
        for key in known[section]:
            value = typed[section].get(key, given.get(key))
            rows.append((section, key, list(value) if isinstance(value, tuple) else value, key in given))
    return rows


def builtin_scene_path(name: str) -> Path:
    """The TOML file of a shipped scene (a key of ``BUILTIN_SCENES``)."""
    return SCENES_DIR / BUILTIN_SCENES[name]


def load_scene(source: str | Path) -> Scene:
    """Read a scene: ``"builtin"``/``"builtin:prostate"``, ``"builtin:calibrated"``, ``"builtin:converged"`` or the
    path of a TOML file.

    A mesh path in the file is taken relative to the scene file. Raises SceneError on anything missing or
    out of range, naming the key and the file.
    """
    name = str(source)
    path = builtin_scene_path(name) if name in BUILTIN_SCENES else Path(name)
    return scene_from_dict(read_scene_toml(path), path)


def read_scene_toml(path: str | Path) -> dict[str, Any]:
    """The parsed TOML of a scene file, with a clear SceneError when it is missing or malformed."""
    path = Path(path)
    if not path.exists() and path.name.startswith("builtin:"):  # a misspelt built-in name, not a file in a folder
        raise SceneError(f"{path.name} is not a built-in scene: give one of {', '.join(BUILTIN_SCENES)}, or a "
                         f"scene TOML path")
    if not path.exists():
        raise SceneError(f"the scene file {path} does not exist: give a TOML path or one of "
                         f"{', '.join(BUILTIN_SCENES)}")
    text = read_text(path, MAX_SCENE_BYTES, "the scene file", SceneError)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"the scene file {path} is not valid TOML: {error}") from error
    except RecursionError:
        raise SceneError(f"the scene file {path} is not valid TOML: it nests too deeply") from None


#: Poisson's ratio of a 10-node (mixed) scene that names none: silicone is nearly incompressible (nu about
#: 0.4999); 0.4996 makes the bulk modulus 1250 times the shear modulus.
QUADRATIC_POISSON_RATIO = 0.4996


def scene_from_dict(raw: dict[str, Any], path: Path | None = None) -> Scene:
    """Build a Scene from a parsed TOML dict; ``path`` anchors relative mesh paths (else the working folder)."""
    where = f"scene {path}" if path else "scene"
    if isinstance(raw.get("model"), str):  # not a [model] table but the model a timeline plays on
        raise SceneError(f"{where} is a timeline scene (its [[steps]] play on the model it names, model = "
                         f"{raw['model']!r}): phantom run-scene and phantom daemon --scene play it; this command wants "
                         f"a model scene ([phantom], [material]), such as the one it names")
    check_known_keys(raw, MODEL_SECTIONS + HOST_SECTIONS, "the file", where)
    for section in MODEL_SECTIONS:
        if section in raw and not isinstance(raw[section], dict):
            raise SceneError(f"{where}: {section} must be a table ([{section}]), got {raw[section]!r}")
    phantom_table = _table(raw, "phantom", where)
    check_known_keys(phantom_table, PHANTOM_KEYS, "[phantom]", where)
    mesh = phantom_table.get("mesh")
    if not isinstance(mesh, str) or not mesh:
        raise SceneError(f"{where}: [phantom] mesh must be 'builtin:prostate' or a mesh file path")
    if not mesh.startswith("builtin:"):
        mesh = str(_beside(mesh, path))
    elif mesh != "builtin:prostate":
        raise SceneError(f"{where}: unknown built-in mesh {mesh!r}: the only one is 'builtin:prostate'")
    geometry = None
    if mesh == "builtin:prostate":
        geometry = geometry_from_table(raw.get("geometry", {}), where)
    elif "geometry" in raw:
        raise SceneError(f"{where}: [geometry] applies to the built-in prostate only; {mesh} is read as it is")
    units = phantom_table.get("units", "mm")
    if not isinstance(units, str) or units not in LENGTH_UNITS_M:
        raise SceneError(f"{where}: [phantom] units = {units!r} is not one of {', '.join(LENGTH_UNITS_M)}")
    chambers = phantom_table.get("chambers")
    if not isinstance(chambers, list) or not chambers or not all(isinstance(c, str) for c in chambers):
        raise SceneError(f"{where}: [phantom] chambers must be a non-empty list of surface group names")
    if len(set(chambers)) != len(chambers):
        raise SceneError(f"{where}: [phantom] chambers lists a group twice: {chambers}")
    fixed = phantom_table.get("fixed")
    if fixed is not None and not isinstance(fixed, str):
        raise SceneError(f"{where}: [phantom] fixed must be a surface group name (or absent)")
    if geometry is not None:  # the built-in mesh's groups are known without meshing it; a mesh file's when read
        for chamber in chambers:
            if chamber not in BUILTIN_CHAMBER_GROUPS:
                raise SceneError(f"{where}: [phantom] chambers names {chamber!r}, which the built-in prostate "
                                 f"lacks: its chambers are {', '.join(BUILTIN_CHAMBER_GROUPS)}")
        if fixed is not None and fixed != BUILTIN_FIXED_GROUP:
            raise SceneError(f"{where}: [phantom] fixed = {fixed!r} is not a group of the built-in prostate: give "
                             f"{BUILTIN_FIXED_GROUP!r} (its fixation patch) or leave the key out")
    steps = raw.get("steps", [])
    if not isinstance(steps, list):
        raise SceneError(f"{where}: steps must be an array of tables ([[steps]]), got {steps!r:.60}")
    return Scene(
        path=path,
        mesh=mesh,
        units=units,
        chambers=list(chambers),
        fixed=fixed,
        material=_material(raw.get("material", {}), where, geometry is not None and geometry.element_order == 2),
        outputs=Outputs(**_outputs(raw.get("outputs", {}), where)),
        chamber_labels=chamber_labels_of(phantom_table, chambers, where),
        model_settings=_model_settings(raw.get("model", {}), where, path),
        load=_load(raw.get("load"), where),
        steps=list(steps),
        raw=raw,
        geometry=geometry,
    )


def _beside(file: str, scene_path: Path | None) -> Path:
    """A file a scene names, absolute: a relative path is taken from the scene file's folder (else the working
    folder)."""
    named = Path(file)
    if not named.is_absolute():
        named = (scene_path.parent if scene_path else Path.cwd()) / named
    return named.resolve()


def _table(raw: dict[str, Any], key: str, where: str) -> dict[str, Any]:
    table = raw.get(key)
    if not isinstance(table, dict):
        raise SceneError(f"{where}: the [{key}] table is missing")
    return table


def _material(table: dict[str, Any], where: str, quadratic: bool = False) -> Material:
    """The [material] table; Poisson's ratio defaults to 0.45 on 4-node elements (which lock near 0.5) and to
    QUADRATIC_POISSON_RATIO, the nearly incompressible silicone, on the built-in mesh's 10-node mixed ones
    (``quadratic``; a mesh file's element order is known only once it is read: such a scene names its ratio)."""
    check_known_keys(table, MATERIAL_KEYS, "[material]", where)
    model = table.get("model", "corotational")
    if model not in MATERIAL_MODELS:
        raise SceneError(f"{where}: [material] model = {model!r}: the hyperelastic laws are 'neo_hookean', "
                         f"'gent' and 'yeoh'; for small strains use 'corotational' or 'linear'")
    gent_jm = table.get("gent_jm")
    if model == "gent":
        locking = "the locking value of I1 - 3 (a positive number, e.g. 20 for silicone)"
        if gent_jm is None:
            raise SceneError(f"{where}: [material] model = 'gent' needs gent_jm, {locking}")
        if not is_finite_number(gent_jm) or not gent_jm > 0:
            raise setting_refused(where, "material", "gent_jm", f"must be {locking}", gent_jm)
        gent_jm = float(gent_jm)
    elif gent_jm is not None:
        raise SceneError(f"{where}: [material] gent_jm applies to model = 'gent' only, not {model!r}")
    yeoh = [table.get(key) for key in YEOH_KEYS]
    if model == "yeoh":
        for key, value in zip(YEOH_KEYS, yeoh, strict=True):
            if not is_finite_number(value):
                raise SceneError(f"{where}: [material] model = 'yeoh' needs {' and '.join(YEOH_KEYS)}, its C20 and "
                                 f"C30 as multiples of C10 = mu/2 (numbers, e.g. 0.05 and 0.001), got {key} = "
                                 f"{value!r}")
    elif any(value is not None for value in yeoh):
        raise SceneError(f"{where}: [material] {' and '.join(YEOH_KEYS)} apply to model = 'yeoh' only, not "
                         f"{model!r}")
    youngs_modulus_kpa = table.get("youngs_modulus_kpa", 50.0)
    poisson_ratio = table.get("poisson_ratio", QUADRATIC_POISSON_RATIO if quadratic else 0.45)
    if not is_finite_number(youngs_modulus_kpa) or not youngs_modulus_kpa > 0:
        raise setting_refused(where, "material", "youngs_modulus_kpa", "must be a positive number", youngs_modulus_kpa)
    low_kpa, high_kpa = YOUNGS_MODULUS_RANGE_KPA
    if not low_kpa <= youngs_modulus_kpa <= high_kpa:
        raise setting_refused(where, "material", "youngs_modulus_kpa",
                              f"must lie in what a silicone or elastomer has, {low_kpa:g} kPa to "
                              f"{high_kpa / 1e3:g} MPa, given in kPa (Ecoflex 00-10: about 50)", youngs_modulus_kpa)
    if isinstance(poisson_ratio, bool) or not isinstance(poisson_ratio, int | float) or not -1.0 < poisson_ratio < 0.5:
        raise setting_refused(where, "material", "poisson_ratio", "must lie in (-1, 0.5)", poisson_ratio)
    return Material(model, float(youngs_modulus_kpa) * 1e3, float(poisson_ratio), gent_jm,
                    *(None if value is None else float(value) for value in yeoh))


def chamber_labels_of(phantom_table: dict[str, Any], chamber_names: list[str], where: str = "scene") -> list[str]:
    """The names people see for the chambers: ``[phantom] chamber_labels`` (one string per chamber; SceneError
    otherwise), else base, left lobe, right lobe for three chambers, else the chambers' surface group names."""
    labels = phantom_table.get("chamber_labels")
    if labels is None:
        three = len(chamber_names) == len(DEFAULT_CHAMBER_LABELS)
        return list(DEFAULT_CHAMBER_LABELS) if three else list(chamber_names)
    if not isinstance(labels, list) or len(labels) != len(chamber_names) or not all(
            isinstance(label, str) and label for label in labels):
        raise SceneError(f"{where}: [phantom] chamber_labels must name each of the {len(chamber_names)} chambers "
                         f"({', '.join(chamber_names)}) with a string, got {labels!r}")
    return list(labels)


def chamber_label(labels: Sequence[str], index: int) -> str:
    """One chamber as every message names it: as ``phantom status`` does, with its index (``left lobe (chamber
    1)``), so that a list of kPa given in chamber order can be matched to it."""
    return f"{labels[index]} (chamber {index})"


def describe_chambers(labels: Sequence[str]) -> str:
    """The chambers in order, as messages list them: ``0 base, 1 left lobe, 2 right lobe``."""
    return ", ".join(f"{index} {label}" for index, label in enumerate(labels))


def pressure_limit_error(pressures_kpa: Sequence[float], labels: Sequence[str],
                         pressure_max_kpa: float | Sequence[float] | None = None) -> str | None:
    """Why chamber pressures (kPa, gauge, in chamber order) are refused, or None when they are not: below 0 (the
    blowers only push) or above ``pressure_max_kpa`` (one or one per chamber; None: checked later, e.g. by the
    inverse against its model's limit). The words the daemon and every command refuse them with."""
    limits: list[float | None]
    if pressure_max_kpa is None or isinstance(pressure_max_kpa, int | float):
        limits = [None if pressure_max_kpa is None else float(pressure_max_kpa)] * len(labels)
    else:
        limits = [float(limit) for limit in pressure_max_kpa]
    problems = []
    for index, (pressure, limit) in enumerate(zip(pressures_kpa, limits, strict=True)):
        if pressure < 0:
            problems.append(f"{chamber_label(labels, index)} at {pressure:g} kPa is below 0 kPa: the blowers only "
                            "push")
        elif limit is not None and pressure > limit:
            problems.append(f"{chamber_label(labels, index)} at {pressure:g} kPa is above the {limit:g} kPa "
                            "limit, which protects the phantom")
    if not problems:
        return None
    return "; ".join(problems) + " (gauge pressures from 0 to the scene's [model] pressure_max_kpa, 3 by default)"


def _positive_number(table: dict[str, Any], key: str, default: float, where: str) -> float:
    value = table.get(key, default)
    if not is_finite_number(value) or not value > 0:
        raise setting_refused(where, "model", key, "must be a positive number", value)
    return float(value)


#: A ``[model] table_volumes`` or ``table_shapes`` value that starts with this names a file the package ships
#: beside its built-in scenes, wherever the scene that names it lies (a copy of an example scene keeps working).
SHIPPED_FILE_PREFIX = "builtin:"


def _shipped_file(table: dict[str, Any], key: str, where: str, path: Path | None) -> Path | None:
    """``[model] key``: a file that response_table wrote (``table_volumes``, ``table_shapes``): beside the scene,
    or ``builtin:NAME``, beside the built-in scenes."""
    value = table.get(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value.removeprefix(SHIPPED_FILE_PREFIX):
        raise SceneError(f"{where}: [model] {key} must be a file path (a .npz that response_table.write_{key} "
                         f"wrote, or builtin:NAME for one beside the built-in scenes), got {value!r}")
    if value.startswith(SHIPPED_FILE_PREFIX):
        name = value.removeprefix(SHIPPED_FILE_PREFIX)
        shipped = sorted(path.name for path in SCENES_DIR.glob("*.npz"))
        if Path(name).name != name:
            raise SceneError(f"{where}: [model] {key} = {value!r}: builtin:NAME names a file in the built-in scenes' "
                             f"folder ({', '.join(shipped)}), not a path; give a path for any other file")
        resolved = SCENES_DIR / name
    else:
        resolved = _beside(value, path)
    if not resolved.is_file():
        built = "the table is then built once per machine" if key == "table_volumes" else "each shape is then solved"
        raise SceneError(f"{where}: [model] {key} names {resolved}, which is not a file: restore it, or remove the "
                         f"key ({built})")
    return resolved


def without_shipped_tables(raw: dict[str, Any]) -> dict[str, Any]:
    """A copy of a scene's TOML dict without the table files it ships (``[model] table_volumes``,
    ``table_shapes``), which belong to its own parameters: for a scene made from it with others (a calibration's,
    a truth at another modulus), or for the build that writes them."""
    document = copy.deepcopy(raw)
    for key in ("table_volumes", "table_shapes"):
        document.get("model", {}).pop(key, None)
    return document


def _model_settings(table: dict[str, Any], where: str, path: Path | None = None) -> ModelSettings:
    if not isinstance(table, dict):
        raise SceneError(f"{where}: [model] must be a table with {', '.join(MODEL_KEYS)}")
    check_known_keys(table, MODEL_KEYS, "[model]", where)
    fidelity = table.get("fidelity")
    if fidelity is not None and fidelity not in FIDELITY_LEVELS:
        raise setting_refused(where, "model", "fidelity", f"must be one of {', '.join(FIDELITY_LEVELS)}", fidelity)
    points = table.get("table_points", DEFAULT_TABLE_POINTS)
    if isinstance(points, bool) or not isinstance(points, int) or points < 2:
        raise setting_refused(where, "model", "table_points", "must be an integer of at least 2", points)
    if points > MAX_TABLE_POINTS:
        raise setting_refused(where, "model", "table_points",
                              f"must be at most {MAX_TABLE_POINTS} (the default {DEFAULT_TABLE_POINTS}'s step "
                              f"halved; the table's build is a full solve per grid point, {points}^3 = "
                              f"{points**3:,} on three chambers)", points)
    pressure_max_kpa = _positive_number(table, "pressure_max_kpa", PRESSURE_LIMIT_PA / 1e3, where)
    if pressure_max_kpa > SENSOR_RANGE_KPA:
        raise SceneError(f"{where}: [model] pressure_max_kpa = {pressure_max_kpa:g} is above the pressure sensor's "
                         f"range (MPXV7025G, 0-{SENSOR_RANGE_KPA:g} kPa): give it in kPa (3 is 3000 Pa)")
    return ModelSettings(fidelity, _positive_number(table, "accuracy_pct", DEFAULT_ACCURACY_PCT, where),
                         pressure_max_kpa * 1e3, points,
                         _shipped_file(table, "table_volumes", where, path),
                         _shipped_file(table, "table_shapes", where, path))


def _load(table: Any, where: str) -> Load:
    if table is None:
        return Load()
    if not isinstance(table, dict):
        raise SceneError(f"{where}: [load] must be a table with density_kg_m3 and gravity_m_s2")
    check_known_keys(table, LOAD_KEYS, "[load]", where)
    density = table.get("density_kg_m3", SILICONE_DENSITY_KG_M3)
    if isinstance(density, bool) or not isinstance(density, int | float) or not 0 < density < 1e5:
        raise setting_refused(where, "load", "density_kg_m3", "must be a positive number (Ecoflex 00-10: 1040)",
                              density)
    gravity = table.get("gravity_m_s2", [0.0, 0.0, -STANDARD_GRAVITY_M_S2])
    if not isinstance(gravity, list) or len(gravity) != 3 or not all(is_finite_number(value) for value in gravity):
        raise setting_refused(where, "load", "gravity_m_s2", "must be three numbers (m/s^2, e.g. [0, 0, -9.81] for "
                              "the built-in prostate hanging from its base)", gravity)
    x, y, z = (float(value) for value in gravity)
    return Load(float(density), (x, y, z))


def _outputs(table: dict[str, Any], where: str) -> dict[str, bool]:
    check_known_keys(table, OUTPUT_KEYS, "[outputs]", where)
    for key, value in table.items():
        if not isinstance(value, bool):
            raise setting_refused(where, "outputs", key, "must be true or false", value)
    return dict(table)
