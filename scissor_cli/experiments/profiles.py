"""Error sources of a simulated trial and their distributions (docs/model.md §10).

A trial draws, from a generator seeded by (seed, target, trial), what a real
bench gets wrong: camera pixel noise, a bias in localising the target, the
true tissue's material against the controller's model (E, ν, η, fiber angle
and a smooth heterogeneity field), actuator resolution and backlash. Trial
k's draw depends only on (seed, target index, k), so any trial can be re-run
alone and the order or the process that runs it does not matter.

Profiles and where their values come from
-----------------------------------------
``prosthesis`` — the paper's silicone prosthesis (§4.2, E = 10 kPa [27]),
observed by a CCD camera through transparent silicone:

* pixel noise σ 0.5 px: centroid noise of a dark target on a clear
  background, typical of blob detection (0.1–0.5 px);
* localisation bias σ 0.3 mm per axis: the target is a 3-D object seen
  through silicone (refraction, its offset from the layer plane);
* E: log-normal, σ(log) 0.10 — batch-to-batch spread of a cast silicone
  around the quoted 10 kPa; ν: ±0.01 (silicone is nearly incompressible);
  η: σ(log) 0.2 and fiber angle σ 10° (silicone has no fibers; the model's
  fiber term is itself a modelling error); heterogeneity σ(log E) 0.05
  (a homogeneous cast);
* actuator: resolution 0.01 mm, backlash 0.02 mm — the paper's T-type micro
  ball-screw slide with a NEMA 11 stepper (1 mm lead, 200 steps, drivers
  microstepping; C7-class screws have 0.01–0.05 mm backlash).

``ex_vivo`` — pork (§4.2), the target a peg whose head is seen on the
surface:

* pixel noise σ 1.0 px: a wet, textured surface;
* localisation bias σ 0.6 mm: the target is inferred from the peg head,
  which tilts and sits above the layer;
* E: σ(log) 0.30 — reported moduli of breast tissue and of porcine fat and
  muscle range from a few kPa to tens of kPa; ν ±0.02; η σ(log) 0.5; fiber
  angle σ 20°; heterogeneity σ(log E) 0.30 (fat, gland, connective tissue);
* actuator as for the prosthesis (same bench).

``ideal`` — nothing: the truth is the controller's model and the
measurement is exact (no pixel rounding). With `trials.count: 1` it is the
deterministic check of the loop.

Needle–tissue interaction (only with an `insertion:` section, docs/model.md
§12): each trial scales the config's friction (static and kinetic by one
factor, so f_k ≤ f_s stays) and its tip force by log-normal factors,
σ(log) ``friction_log_sd`` and ``tip_force_log_sd``:

* prosthesis 0.2 and 0.2: a cast silicone phantom is repeatable, but
  friction depends on insertion speed and surface state (DiMaio &
  Salcudean 2003 measured the force along the shaft in a PVC phantom;
  Okamura et al. 2004 show friction changing with speed in liver);
* ex_vivo 0.4 and 0.4: tissue-to-tissue spread of pork (fat, muscle,
  fascia); needle forces in soft tissue vary by a factor of ~2 between
  samples and sites (Abolhassani et al. 2007 review). These spreads are
  assumptions of the order those papers show, not fitted values.

They are drawn from a stream of their own (seeded by seed, target, trial and
a fixed tag), so a scene without insertion draws exactly what it drew before.

Ultrasound (only with an `imaging:` section, docs/model.md §17): with
imaging the camera's sources (pixel noise, localisation bias) do not
apply; the ultrasound sensor draws its own (`sensing.ultrasound.
imaging_sensor`), on streams of its own, so a scene without imaging draws
exactly what it drew before:

* ``sound_speed_sd_m_per_s``: σ of the tissue's speed of sound about
  `imaging.sound_speed_m_per_s` (the scanner keeps its assumed speed; the
  time of flight then moves the lesion along the beam by depth ×
  (c_assumed / c_tissue − 1)). prosthesis 10 m/s: an ultrasound phantom is
  made of a tissue-mimicking material whose speed is specified or measured
  (e.g. the CIRS breast phantoms' Zerdine gel, 1540 ± 10 m/s; agar and
  gelatin recipes are tuned to ±10 m/s). ex_vivo 35 m/s: the beam crosses
  fat and gland or muscle in unknown shares — breast fat ≈ 1450–1470 m/s,
  fibroglandular tissue ≈ 1510–1570 m/s (and porcine fat and muscle about
  the same), so a path's mean speed lies anywhere in a ≈ 120 m/s range,
  whose σ as a uniform spread is 120 / √12 ≈ 35 m/s;
* ``probe_position_sd_mm``, ``probe_angle_sd_deg``: the probe's pose as
  the scanner believes it against where it sits (per axis, and the beam's
  angle). prosthesis and ex_vivo 0.2 mm and 0.5°: a probe clamped in a
  machined holder on the robot and calibrated with a phantom; freehand
  tracked-probe calibrations reach about 0.5–1 mm RMS (Mercier et al.
  2005 review), a rigid mount registered to the bench does better; the
  same bench for both profiles;
* ``electronic_noise_scale``: the electronic noise's amplitude relative
  to `imaging.snr_db` (1: the configured SNR; 0: none). 1 for prosthesis
  and ex_vivo: the scanner's noise is the same on both;
* the speckle realisation (the scatterers' draw) is always there: a trial
  draws its own tissue.

``ideal`` has none of them (the tissue's speed is the configured one,
matched to the scanner's in the example scenes; a configured mismatch is a
property of the scene and applies in every profile).

A 3-D scene's own sources (docs/model.md §20, "Budget"), 0 in every
profile because neither the paper nor its bench reports them, drawn on a
stream of their own (`draw_body`):

* ``registration_mm``, ``registration_deg``: the body's registration in
  the robot's frame, σ of its offset per axis and of its rotation about
  each axis (about the body's origin). The needle goes in along the
  planned line moved by that error; the loop, which sees the lesion with
  the camera(s), does not know it. A fiducial-based registration of a
  phantom reaches about 1 mm target registration error; set it to the
  setup's own;
* ``lesion_stiffness_log_sd``: σ of the log of a factor on the lesion's
  stiffness (its region's E, `targets[].stiffness_factor`), which imaging
  does not measure well (elastography reports 2–5× the fat's E for
  benign and malignant lesions alike).

``release_slip_mm`` (default 0 in every profile) is an optional extra source:
the tissue slipping in the cup along the push axis after the loop stops,
which the paper names as its main error (no prone position, no vertical
restraint). It is off by default because nothing measures it; the README
compares the simulated errors with the paper's without it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scissor_cli.config import TrialsConfig
from scissor_cli.geometry3d import rotation_matrix

PROFILES: dict[str, dict[str, float]] = {
    "ideal": dict(
        pixel_noise_px=0.0, localisation_error_mm=0.0, E_log_sd=0.0, nu_sd=0.0, eta_log_sd=0.0,
        fiber_angle_sd_deg=0.0, heterogeneity_log_sd=0.0, actuator_resolution_mm=0.0, backlash_mm=0.0,
        release_slip_mm=0.0, friction_log_sd=0.0, tip_force_log_sd=0.0,
        sound_speed_sd_m_per_s=0.0, probe_position_sd_mm=0.0, probe_angle_sd_deg=0.0, electronic_noise_scale=0.0,
        registration_mm=0.0, registration_deg=0.0, lesion_stiffness_log_sd=0.0,
    ),
    "prosthesis": dict(
        pixel_noise_px=0.5, localisation_error_mm=0.3, E_log_sd=0.10, nu_sd=0.01, eta_log_sd=0.2,
        fiber_angle_sd_deg=10.0, heterogeneity_log_sd=0.05, actuator_resolution_mm=0.01, backlash_mm=0.02,
        release_slip_mm=0.0, friction_log_sd=0.2, tip_force_log_sd=0.2,
        sound_speed_sd_m_per_s=10.0, probe_position_sd_mm=0.2, probe_angle_sd_deg=0.5, electronic_noise_scale=1.0,
        registration_mm=0.0, registration_deg=0.0, lesion_stiffness_log_sd=0.0,
    ),
    "ex_vivo": dict(
        pixel_noise_px=1.0, localisation_error_mm=0.6, E_log_sd=0.30, nu_sd=0.02, eta_log_sd=0.5,
        fiber_angle_sd_deg=20.0, heterogeneity_log_sd=0.30, actuator_resolution_mm=0.01, backlash_mm=0.02,
        release_slip_mm=0.0, friction_log_sd=0.4, tip_force_log_sd=0.4,
        sound_speed_sd_m_per_s=35.0, probe_position_sd_mm=0.2, probe_angle_sd_deg=0.5, electronic_noise_scale=1.0,
        registration_mm=0.0, registration_deg=0.0, lesion_stiffness_log_sd=0.0,
    ),
}

#: Fourier features of the heterogeneity field (random-feature approximation
#: of a Gaussian-covariance random field with unit variance)
N_FEATURES = 64
NU_MAX = 0.499


@dataclass(frozen=True)
class ErrorModel:
    """The resolved distributions of one run: the profile with the config's overrides."""

    profile: str
    pixel_noise_px: float
    localisation_error_mm: float
    E_log_sd: float
    nu_sd: float
    eta_log_sd: float
    fiber_angle_sd_deg: float
    heterogeneity_log_sd: float
    heterogeneity_length_mm: float
    actuator_resolution_mm: float
    backlash_mm: float
    release_slip_mm: float
    friction_log_sd: float = 0.0
    tip_force_log_sd: float = 0.0
    sound_speed_sd_m_per_s: float = 0.0
    probe_position_sd_mm: float = 0.0
    probe_angle_sd_deg: float = 0.0
    electronic_noise_scale: float = 0.0
    registration_mm: float = 0.0
    registration_deg: float = 0.0
    lesion_stiffness_log_sd: float = 0.0

    @property
    def exact_measurement(self) -> bool:
        return self.profile == "ideal" and self.pixel_noise_px == 0 and self.localisation_error_mm == 0


def error_model(trials: TrialsConfig) -> ErrorModel:
    values = dict(PROFILES[trials.profile])
    for key in values:
        override = getattr(trials, key)
        if override is not None:
            values[key] = float(override)
    return ErrorModel(profile=trials.profile, heterogeneity_length_mm=trials.heterogeneity_length_mm, **values)


@dataclass(frozen=True)
class TrialDraw:
    """What trial k of one target gets wrong, drawn once before its loop runs.

    E_field (M,) multiplies the model's per-element E; rng is the trial's own
    stream for the measurements inside the loop.
    """

    E_field: np.ndarray
    nu: float
    eta_scale: float
    fiber_offset_rad: float
    localisation_z: np.ndarray  # (2,) standard normals: the sensor scales them into its localisation bias
    release_slip_mm: float
    rng: np.random.Generator


def trial_rng(seed: int, target_index: int, trial: int) -> np.random.Generator:
    """The generator of one trial: depends only on (seed, target, trial)."""
    return np.random.default_rng([int(seed), int(target_index), int(trial)])


def smooth_field(centroids: np.ndarray, length_mm: float, rng: np.random.Generator) -> np.ndarray:
    """A zero-mean, unit-variance random field (M,) at centroids (M, d) (d = 2, or 3 in a body), correlation length
    in mm."""
    omega = rng.standard_normal((N_FEATURES, centroids.shape[1])) / length_mm
    phase = rng.uniform(0.0, 2.0 * np.pi, N_FEATURES)
    return np.sqrt(2.0 / N_FEATURES) * np.cos(centroids @ omega.T + phase).sum(axis=1)


def draw_trial(model: ErrorModel, nu_model: float, centroids: np.ndarray, seed: int, target_index: int,
               trial: int) -> TrialDraw:
    """Draw one trial's error sources; the same arguments give the same draw."""
    rng = trial_rng(seed, target_index, trial)
    # Every draw is made whatever its σ, so changing one σ does not shift the others.
    z = rng.standard_normal(5)
    field = smooth_field(centroids, model.heterogeneity_length_mm, rng)
    localisation_z = rng.standard_normal(2)
    slip = float(rng.standard_normal()) * model.release_slip_mm
    return TrialDraw(
        E_field=np.exp(model.E_log_sd * z[0] + model.heterogeneity_log_sd * field),
        nu=float(np.clip(nu_model + model.nu_sd * z[1], -0.99, NU_MAX)),
        eta_scale=float(np.exp(model.eta_log_sd * z[2])),
        fiber_offset_rad=float(np.deg2rad(model.fiber_angle_sd_deg) * z[3]),
        localisation_z=localisation_z,
        release_slip_mm=slip,
        rng=np.random.default_rng(rng.integers(0, 2**63 - 1)),
    )


#: the ErrorModel fields only a 3-D scene uses (and stores)
BODY_SPREADS = ("registration_mm", "registration_deg", "lesion_stiffness_log_sd")
#: the tag of the 3-D sources' own stream
BODY_STREAM = 14


@dataclass(frozen=True)
class BodyDraw:
    """A 3-D trial's own sources: the registration's offset (3,) mm and rotation (3,) rad (about x, y, z) of the
    body in the robot's frame, and the factor on the lesion's stiffness."""

    offset_mm: np.ndarray
    rotation_rad: np.ndarray
    lesion_stiffness: float

    def moved(self, points: np.ndarray) -> np.ndarray:
        """Points (K, 3) mm of the body's frame where the robot, registered with this error, puts them."""
        return np.atleast_2d(points) @ self.rotation.T + self.offset_mm

    @property
    def registered_exactly(self) -> bool:
        return not (np.any(self.offset_mm) or np.any(self.rotation_rad))

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3): the rotation by the rotation vector `rotation_rad`."""
        return rotation_matrix(self.rotation_rad)


def draw_body(model: ErrorModel, seed: int, target_index: int, trial: int) -> BodyDraw:
    """Trial k's 3-D sources (docs/model.md §20, "Budget"), on a stream of their own: the other draws stay."""
    z = np.random.default_rng([int(seed), int(target_index), int(trial), BODY_STREAM]).standard_normal(7)
    return BodyDraw(model.registration_mm * z[:3], np.deg2rad(model.registration_deg) * z[3:6],
                    float(np.exp(model.lesion_stiffness_log_sd * z[6])))


#: the ErrorModel fields that only a scene with insertion uses (and stores)
INSERTION_SPREADS = ("friction_log_sd", "tip_force_log_sd")
#: the tag of the insertion draws' own stream
INSERTION_STREAM = 12
#: the ErrorModel fields that only a scene with imaging uses (and stores); the camera's it then does not
IMAGING_SPREADS = ("sound_speed_sd_m_per_s", "probe_position_sd_mm", "probe_angle_sd_deg", "electronic_noise_scale")
CAMERA_SPREADS = ("pixel_noise_px", "localisation_error_mm")


def trial_needle(base, model: ErrorModel, seed: int, target_index: int, trial: int):
    """The config's `insertion.NeedleParams` with trial k's factors (`draw_insertion`) on its friction and tip force."""
    f_scale, tip_scale = draw_insertion(model, seed, target_index, trial)
    return replace(base, friction_static_mN_per_mm=base.friction_static_mN_per_mm * f_scale,
                   friction_kinetic_mN_per_mm=base.friction_kinetic_mN_per_mm * f_scale,
                   tip_force_mN=base.tip_force_mN * tip_scale)


def draw_insertion(model: ErrorModel, seed: int, target_index: int, trial: int) -> tuple[float, float]:
    """Trial k's factors (friction, tip force) on the config's needle forces, log-normal (docs/model.md §12)."""
    z = np.random.default_rng([int(seed), int(target_index), int(trial), INSERTION_STREAM]).standard_normal(2)
    return float(np.exp(model.friction_log_sd * z[0])), float(np.exp(model.tip_force_log_sd * z[1]))
