"""One trial's scatterers: drawn in the rest region a frame can see, carried by the true tissue (docs/ultrasound.md §6).

The region is the frame's grid (a window, or the whole image) taken back
to the layer through the probe's true pose at the tissue's sound speed
(apparent depth x c_tissue / c_assumed is the true depth), widened by the
target's travel and `REGION_SLACK_MM` (tissue moving into view, the PSF's
reach beyond the grid), and cut to the mesh's extent. Scatterers outside
the mesh are dropped.

In the layer every scatterer lies in the imaging plane and the lesion is a
disc. In the slab the scatterers fill an elevation band ±b about the
layer's height (`elevation_band_mm`): b reaches where the two-way
elevation amplitude of the deepest row of the grid falls to -20 dB
(`ELEVATION_EDGE_NEPER`) plus `ELEVATION_MARGIN_MM` for tissue moving
across the plane, within the slab; the in-plane density is raised by
2b / (the elevation beam's -6 dB thickness at the lesion's depth) so that
the beam holds as many scatterers per resolution cell as the layer's
plane; the lesion is a sphere. Drawn once per kind of mesh (layer or
slab), on the trial's speckle stream, when the first frame asks.
"""

from __future__ import annotations

import math

import numpy as np

from scissor_cli.sensing.sensor import TrueState
from scissor_cli.sensing.ultrasound.fast import FrameKernels
from scissor_cli.sensing.ultrasound.psf import SCATTERERS_PER_CELL
from scissor_cli.sensing.ultrasound.scatterer_motion import CarriedScatterers, carry_on, is_slab
from scissor_cli.sensing.ultrasound.scatterers import draw_scatterers
from scissor_cli.sensing.ultrasound.transducer import ProbePose

#: the rest region reaches this far (mm) beyond the grid's footprint and the travel: tissue moving into view,
#: and the PSF's reach (a scatterer outside the grid still lights its edge)
REGION_SLACK_MM = 3.0
#: the elevation band's edge: two-way amplitude exp(-coef y^2) = exp(-ELEVATION_EDGE_NEPER), i.e. -20 dB
ELEVATION_EDGE_NEPER = math.log(10.0)
#: added to the band for tissue moving across the plane (mm)
ELEVATION_MARGIN_MM = 0.5


def elevation_band_mm(kernels: FrameKernels, below_mm: float = math.inf, above_mm: float = math.inf) -> float:
    """Half-width b (mm) of the elevation band for frames on these kernels' grid (module docstring).

    below_mm, above_mm: the room under and over the imaging plane (the
    slab's extent about the layer); b stays within both.
    """
    coef = float(np.min(kernels.elevation_coef_re))
    b = math.sqrt(ELEVATION_EDGE_NEPER / max(coef, 1e-9)) + ELEVATION_MARGIN_MM
    return float(max(0.0, min(b, below_mm, above_mm)))


class ScatterScene:
    """A trial's scatterers: their draw per kind of mesh and their carriage per mesh, shared by reseeded copies.

    model: the run's `UltrasoundModel` (read: tables, lesion, obstacles);
    rest_mm (2,): the lesion's centre; speckle_key: the seed of the speckle
    stream; kernels: the frames' tables (their grid); pose: the probe's true
    pose; tissue speed (m/s); travel_mm: the target's expected travel;
    per_cell: scatterers per resolution cell.
    """

    def __init__(self, model, rest_mm: np.ndarray, speckle_key: tuple, kernels: FrameKernels, pose: ProbePose,
                 tissue_sound_speed_m_per_s: float, travel_mm: float, per_cell: float = SCATTERERS_PER_CELL):
        self.model, self.rest_mm, self.key = model, np.asarray(rest_mm, float), tuple(speckle_key)
        self.kernels, self.grid, self.pose = kernels, kernels.grid, pose
        self.c_t, self.travel_mm, self.per_cell = float(tissue_sound_speed_m_per_s), float(travel_mm), per_cell
        self._draws: dict[bool, tuple] = {}  # slab? -> (positions (S0, 2), elevation (S0,), amplitude (S0,))
        self._carried: list[tuple[object, CarriedScatterers, np.ndarray]] = []  # (mesh, carriage, amplitude)

    def in_probe_frame(self, state: TrueState) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(lateral, true depth, elevation) mm and amplitude (S,) of the scatterers in the true state."""
        if state.nodes_mm is None or state.mesh is None:
            raise ValueError("the ultrasound sensor needs the true tissue's nodes and mesh (TrueState.nodes_mm, .mesh)")
        carried, amplitude = self._carriage(state.mesh)
        lat, dep, ele = carried.to_probe(state.nodes_mm, self.pose)
        return lat, dep, ele, amplitude

    def _carriage(self, mesh) -> tuple[CarriedScatterers, np.ndarray]:
        for known, carried, amplitude in self._carried:
            if known is mesh:
                return carried, amplitude
        pos, ele, amp = self._draw(mesh)
        carried = carry_on(mesh, pos, ele)
        amplitude = np.ascontiguousarray(amp[carried.kept])
        self._carried = self._carried[-1:] + [(mesh, carried, amplitude)]  # the last two meshes seen
        return carried, amplitude

    def _draw(self, mesh) -> tuple:
        slab = is_slab(mesh)
        if slab in self._draws:
            return self._draws[slab]
        m = self.model
        psf = m.tables.psf
        plane = mesh.plane if slab else mesh
        region = self.region_mm(np.asarray(plane.nodes, float))
        density = psf.density_per_mm2(self.per_cell)
        band = 0.0
        if slab:
            levels = np.asarray(mesh.levels_mm, float)
            z = float(levels[mesh.layer_level])
            band = elevation_band_mm(self.kernels, z - levels[0], levels[-1] - z)
            depth = float(np.clip(self.pose.to_probe(self.rest_mm)[1], psf.depths_mm[0], psf.depths_mm[-1]))
            if band > 0:
                density *= max(1.0, 2.0 * band / float(psf.elevation_fwhm_mm(depth)))
        rng = np.random.default_rng(self.key)
        if region is None:
            out = (np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.float32))
        else:
            sc = draw_scatterers(rng, region, density, band, self.rest_mm, m.lesion_radius_mm, m.lesion_echogenicity_db,
                                 m.obstacles, 0.0)
            out = (sc.positions_mm, sc.elevation_mm, sc.amplitude)
        self._draws[slab] = out
        return out

    def region_mm(self, mesh_nodes_mm: np.ndarray):
        """The rest box [[x0, y0], [x1, y1]] mm the scatterers are drawn in (module docstring), None if empty."""
        g = self.grid
        c_a = self.model.tables.psf.sound_speed_m_per_s
        depth = np.array([g.depth_mm[0], g.depth_mm[-1]]) * self.c_t / c_a
        corners = np.array([[x, z] for x in (g.lateral_mm[0], g.lateral_mm[-1]) for z in depth])
        layer = self.pose.to_layer(corners)
        grow = self.travel_mm + REGION_SLACK_MM
        lo = np.maximum(layer.min(axis=0) - grow, mesh_nodes_mm.min(axis=0))
        hi = np.minimum(layer.max(axis=0) + grow, mesh_nodes_mm.max(axis=0))
        if not np.all(hi - lo > 1e-6):
            return None
        return np.array([lo, hi])
