"""The puncture module as a serial chain: DH links, forward kinematics, closed form (docs/model.md §11).

Paper §2.3, Table 2. A modified (Craig) Denavit–Hartenberg chain,

    ᶦ⁻¹T_i = Rot_x(α_{i−1}) · Trans_x(a_{i−1}) · Rot_z(θ_i) · Trans_z(d_i),

built from a table of links. The paper's table has six links and five
actuated joints, ordered everywhere as

    q = (d1, d2, d3, θ4, d5)        mm, mm, mm, rad, mm

Multiplying the paper's six matrices out (done symbolically and checked in
the tests to 1e-9 mm) gives exactly the closed form printed in docs/model.md §11:

    tip  = (a1 + d3 − (d5+d6) cos θ4,  a3 + d2 − (d5+d6) sin θ4,  d1 + a5)
    axis = (−cos θ4, −sin θ4, 0)        (tool z = approach = travel direction)

so the needle lies in a horizontal plane and ``tip = C + (d5+d6)·axis`` with
the arc-RCM centre ``C = (a1+d3, a3+d2, d1+a5)``.

Conventions of the `robot` package:

* For an actuated joint the table's own θ (revolute) or d (prismatic) entry
  is a constant offset added to the joint value; the paper's offsets are 0.
* Angles are radians here; `RobotModel.from_config` converts the config's
  degrees.
* The closed form is used whenever the table has the paper's structure
  (dimensions, offsets and limits may differ); that is decided by comparing
  it with the matrix product, so a table it does not describe falls back to
  the product automatically. Inverse kinematics (`robot.ik`) and the
  sample-free workspace coverage need it (`RobotModel.require_closed_form`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from scissor_cli.config import RobotConfig

JOINT_KINDS = ("revolute", "prismatic", "fixed")

#: Feasibility slack on joint limits (mm or rad): absorbs round-off so that a
#: configuration exactly on a limit is still reachable after FK → IK.
LIMIT_TOL = 1e-10


# --------------------------------------------------------------------------- #
# The DH table
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class DHLink:
    """One row of a modified-DH table.

    alpha_rad, a_mm: α_{i−1}, a_{i−1} (twist and length of the previous link).
    theta_rad, d_mm: θ_i, d_i; for the actuated one of the two it is the
        offset added to the joint value.
    joint: "revolute" (θ_i moves), "prismatic" (d_i moves) or "fixed".
    lower, upper: joint limits of the joint value, rad or mm; None if fixed.
    name: joint name used in reports; default "theta<i>" / "d<i>".
    """

    alpha_rad: float
    a_mm: float
    theta_rad: float
    d_mm: float
    joint: str = "fixed"
    lower: Optional[float] = None
    upper: Optional[float] = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.joint not in JOINT_KINDS:
            raise ValueError(f"DH joint must be one of {JOINT_KINDS}, got {self.joint!r}")
        if self.joint != "fixed":
            if self.lower is None or self.upper is None:
                raise ValueError(f"a {self.joint} DH joint needs lower and upper limits")
            if not self.lower <= self.upper:
                raise ValueError(f"DH joint limits must satisfy lower <= upper, got [{self.lower}, {self.upper}]")


def link_transform(alpha: float, a: float, theta, d) -> np.ndarray:
    """ᶦ⁻¹T_i for scalars or (M,) arrays of theta / d → (4,4) or (M,4,4).

    Rot_x(α)·Trans_x(a)·Rot_z(θ)·Trans_z(d) multiplied out (Craig eq. 3.6).
    """
    theta = np.asarray(theta, dtype=float)
    d = np.asarray(d, dtype=float)
    shape = np.broadcast_shapes(theta.shape, d.shape)
    ca, sa = np.cos(alpha), np.sin(alpha)
    ct, st = np.cos(theta), np.sin(theta)
    T = np.zeros(shape + (4, 4))
    T[..., 0, 0] = ct
    T[..., 0, 1] = -st
    T[..., 0, 3] = a
    T[..., 1, 0] = st * ca
    T[..., 1, 1] = ct * ca
    T[..., 1, 2] = -sa
    T[..., 1, 3] = -sa * d
    T[..., 2, 0] = st * sa
    T[..., 2, 1] = ct * sa
    T[..., 2, 2] = ca
    T[..., 2, 3] = ca * d
    T[..., 3, 3] = 1.0
    return T


def paper_links() -> tuple[DHLink, ...]:
    """Table 2 of the paper as corrected in docs/model.md §11."""
    m90 = -np.pi / 2
    return (
        DHLink(0.0, 0.0, 0.0, 0.0, "prismatic", 0.0, 430.0, "d1"),
        DHLink(m90, 60.0, m90, 0.0, "prismatic", 0.0, 200.0, "d2"),
        DHLink(m90, 0.0, m90, 0.0, "prismatic", 0.0, 150.0, "d3"),
        DHLink(m90, 70.0, 0.0, 0.0, "revolute", np.deg2rad(-135.0), np.deg2rad(45.0), "theta4"),
        DHLink(m90, 0.0, m90, 0.0, "prismatic", 0.0, 80.0, "d5"),
        DHLink(0.0, 80.0, 0.0, 80.0, "fixed", None, None, "tool"),
    )


@dataclass(frozen=True)
class ClosedForm:
    """Parameters of the paper-structure closed form (docs/model.md §11).

    a1, a3, a5, d6 (mm): the table's constant lengths that enter the closed
    form; offsets (5,): the table's entries added to q = (d1, d2, d3, θ4, d5),
    in mm, mm, mm, rad, mm.
    """

    a1: float
    a3: float
    a5: float
    d6: float
    offsets: np.ndarray  # (5,) added to q: d1, d2, d3 (mm), θ4 (rad), d5 (mm)


_PAPER_KINDS = ("prismatic", "prismatic", "prismatic", "revolute", "prismatic", "fixed")


def _closed_tip_axis(q: np.ndarray, cf: ClosedForm) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form tip (M,3) mm and approach axis (M,3) for q (M,5)."""
    D = q + cf.offsets
    c, s = np.cos(D[:, 3]), np.sin(D[:, 3])
    reach = D[:, 4] + cf.d6
    tip = np.empty((q.shape[0], 3))
    tip[:, 0] = cf.a1 + D[:, 2] - reach * c
    tip[:, 1] = cf.a3 + D[:, 1] - reach * s
    tip[:, 2] = D[:, 0] + cf.a5
    axis = np.zeros((q.shape[0], 3))
    axis[:, 0] = -c
    axis[:, 1] = -s
    return tip, axis


@dataclass(frozen=True)
class RobotModel:
    """A serial chain: DH links plus a constant tool transform (4,4).

    `fk` and `tip_and_axis` take q of shape (n,) or (M,n), n = number of
    actuated joints in table order (paper: d1, d2, d3, θ4, d5).
    """

    links: tuple[DHLink, ...]
    tool: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = "custom"
    #: the closed form when the table has the paper's structure (set on construction), else None
    closed_form: Optional[ClosedForm] = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        links = []
        for i, link in enumerate(self.links, start=1):
            if not link.name and link.joint != "fixed":
                prefix = "theta" if link.joint == "revolute" else "d"
                link = DHLink(link.alpha_rad, link.a_mm, link.theta_rad, link.d_mm,
                              link.joint, link.lower, link.upper, f"{prefix}{i}")
            links.append(link)
        object.__setattr__(self, "links", tuple(links))
        tool = np.asarray(self.tool, dtype=float)
        if tool.shape != (4, 4):
            raise ValueError(f"tool must be a (4,4) transform, got shape {tool.shape}")
        object.__setattr__(self, "tool", tool)
        if self.n_joints == 0:
            raise ValueError("a robot needs at least one actuated joint")
        object.__setattr__(self, "closed_form", self._detect_closed_form())

    # -- construction ------------------------------------------------------ #

    @classmethod
    def paper(cls) -> "RobotModel":
        """The puncture module of the paper (Table 2, docs/model.md §11)."""
        return cls(paper_links(), name="paper")

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> "RobotModel":
        """From a robot config section: `cfg.dh` None → paper table.

        Each `cfg.dh` item has alpha_deg, a_mm, theta_deg, d_mm, joint and
        limits ((lo, hi) in mm for prismatic, deg for revolute; None if fixed).
        """
        rows = getattr(cfg, "dh", None)
        if rows is None:
            return cls.paper()
        links = []
        for row in rows:
            kind = str(getattr(row.joint, "value", row.joint))
            lo = hi = None
            if kind != "fixed":
                if row.limits is None:
                    raise ValueError(f"DH row with a {kind} joint needs limits")
                lo, hi = (float(v) for v in row.limits)
                if kind == "revolute":
                    lo, hi = np.deg2rad(lo), np.deg2rad(hi)
            links.append(DHLink(np.deg2rad(float(row.alpha_deg)), float(row.a_mm),
                                np.deg2rad(float(row.theta_deg)), float(row.d_mm), kind, lo, hi))
        return cls(tuple(links), name="config")

    # -- joint metadata ---------------------------------------------------- #

    @property
    def actuated(self) -> tuple[DHLink, ...]:
        return tuple(link for link in self.links if link.joint != "fixed")

    @property
    def n_joints(self) -> int:
        return len(self.actuated)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(link.name for link in self.actuated)

    @property
    def revolute_mask(self) -> np.ndarray:
        """(n,) bool: True where the joint value is an angle (rad)."""
        return np.array([link.joint == "revolute" for link in self.actuated])

    @property
    def lower(self) -> np.ndarray:
        """(n,) lower joint limits, mm or rad."""
        return np.array([link.lower for link in self.actuated], dtype=float)

    @property
    def upper(self) -> np.ndarray:
        """(n,) upper joint limits, mm or rad."""
        return np.array([link.upper for link in self.actuated], dtype=float)

    @property
    def has_closed_form(self) -> bool:
        return self.closed_form is not None

    def require_closed_form(self) -> ClosedForm:
        """The closed form; NotImplementedError for a table without the paper's structure.

        Inverse kinematics and the sample-free workspace coverage are solved
        in closed form only, so they call this first.
        """
        if self.closed_form is None:
            raise NotImplementedError(
                "inverse kinematics is closed-form for the paper's chain structure "
                "(P,P,P,R,P + fixed tool with the twists of Table 2); this DH table differs"
            )
        return self.closed_form

    def within_limits(self, q, tol: float = LIMIT_TOL) -> np.ndarray:
        """(M,) bool: every joint of q (M,n) inside its limits (± tol)."""
        q = self._as_batch(q)
        return np.all((q >= self.lower - tol) & (q <= self.upper + tol), axis=1)

    # -- forward kinematics ------------------------------------------------ #

    def _as_batch(self, q) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            q = q[None, :]
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise ValueError(f"q must have shape ({self.n_joints},) or (M, {self.n_joints}), got {q.shape}")
        return q

    def fk(self, q) -> np.ndarray:
        """Tool frame in the base frame, (M,4,4), for q (n,) or (M,n).

        A batched product over the links; constant links stay (4,4) and
        broadcast, so only the actuated ones cost M matrices each.
        """
        q = self._as_batch(q)
        T = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4))
        j = 0
        for link in self.links:
            theta, d = link.theta_rad, link.d_mm
            if link.joint == "revolute":
                theta = theta + q[:, j]
                j += 1
            elif link.joint == "prismatic":
                d = d + q[:, j]
                j += 1
            T = T @ link_transform(link.alpha_rad, link.a_mm, theta, d)
        return T @ self.tool

    def tip_and_axis(self, q) -> tuple[np.ndarray, np.ndarray]:
        """Needle tip (M,3) mm and unit approach axis (M,3) for q (n,) or (M,n).

        Closed form for the paper's structure, else the tool frame's origin
        and z column from `fk`.
        """
        q = self._as_batch(q)
        if self.closed_form is not None:
            return _closed_tip_axis(q, self.closed_form)
        T = self.fk(q)
        return T[:, :3, 3].copy(), T[:, :3, 2].copy()

    def _detect_closed_form(self) -> Optional[ClosedForm]:
        # The closed form is trusted only where it reproduces the product.
        L = self.links
        if len(L) != 6 or tuple(link.joint for link in L) != _PAPER_KINDS:
            return None
        cf = ClosedForm(a1=L[1].a_mm, a3=L[3].a_mm, a5=L[5].a_mm, d6=L[5].d_mm,
                         offsets=np.array([L[0].d_mm, L[1].d_mm, L[2].d_mm, L[3].theta_rad, L[4].d_mm]))
        rng = np.random.default_rng(12345)
        lo, hi = self.lower, self.upper
        q = np.vstack([lo, hi, rng.uniform(lo, hi, size=(16, 5)), rng.uniform(-500, 500, size=(8, 5))])
        T = self.fk(q)
        tip, axis = _closed_tip_axis(q, cf)
        scale = 1.0 + np.abs(T[:, :3, 3]).max()
        if (np.allclose(tip, T[:, :3, 3], rtol=0, atol=1e-9 * scale)
                and np.allclose(axis, T[:, :3, 2], rtol=0, atol=1e-12)):
            return cf
        return None
