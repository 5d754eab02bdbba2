"""The linear calibration formulation for six-parameter (PRY) modules (seed 000 ch. 4, ch. 6.1).

Error model Delta X = J Delta g (eq 4.1): Delta g holds six increments per module, (dx, dy, dz)
on the static body vector b_s and (dp, dr, ds) on its static rotation R_s; Delta X is the tip
position error (eq 4.5-4.6, "position" scheme) or position and orientation error (eq 4.2-4.4,
"pose" scheme) at m measured configurations. J is the autodiff Jacobian of the model's tip pose
with respect to the increments of the chosen update rule, so each category's step is exact to
first order (the seed uses one geometric Jacobian, eq 4.3b, for both updates). Delta g is the
pseudo-inverse solution (minimum-norm for m = 1, eq 4.26; least squares for many poses, eq 4.27;
SVD, so rank-deficient module sets are handled too), and the loop of Figure 4.1 repeats
model -> error -> J -> Delta g -> update until RMSE <= tol, recording RMSPE, RMSOE, RMSE (eq 4.31).

The four categories of Table 4.1 (numbers as read from the OCR'd table):

| category | tip orientation error                                   | update of R_s                     |
|----------|---------------------------------------------------------|-----------------------------------|
| 1        | vect(delta), delta = (R_m - R_n) R_n^T (eq 4.15-4.20)   | R_s (I + skew(d)) (eq 4.30)       |
| 2        | Phi(theta_n) (theta_m - theta_n), theta = f^-1(R) (4.21-4.25) | R_s (I + skew(d)) (eq 4.30) |
| 3        | vect(delta)                                             | R_s = R_pry(theta + d) (eq 4.29)  |
| 4        | Phi(theta_n) (theta_m - theta_n)                        | R_s = R_pry(theta + d) (eq 4.29)  |

Their two failure modes: the skew update leaves R_s non-orthogonal (`orthogonality` records
max_i ||R_s,i^T R_s,i - I||_F per iteration), and the PRY difference depends on the branch the
inverse f^-1 returns (eq 3.18-3.21, Table 3.1): where the measured and nominal tip angles fall on
different branches (a +-180 deg wrap of theta_x or theta_z, or any angle outside eq 3.18's first
quadrant) the difference is off by up to 2 pi.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.kin.joints.pry import PRY, pry_motion
from jaxcal.kin.model import Robot
from jaxcal.kin.rotations import matrix_to_pry, matrix_to_pry_acos, matrix_to_pry_atan2, pry_to_matrix, skew, vect

CATEGORIES = {1: ("vect", "skew"), 2: ("pry", "skew"), 3: ("vect", "pry"), 4: ("pry", "pry")}
INVERSES = {"atan2": matrix_to_pry_atan2, "acos": matrix_to_pry_acos, "safe": matrix_to_pry}
SCHEMES = ("position", "pose")


@dataclasses.dataclass(frozen=True)
class Chain:
    """Static structure of a serial PRY-module robot: joint kinds, joint-input indices, base frame."""

    kinds: tuple[str, ...]
    inputs: tuple[tuple[int, ...], ...]
    base_R: np.ndarray
    base_p: np.ndarray

    def __hash__(self):
        return hash((self.kinds, self.inputs, self.base_R.tobytes(), self.base_p.tobytes()))

    def __eq__(self, other):
        return isinstance(other, Chain) and hash(self) == hash(other)


@dataclasses.dataclass(frozen=True)
class ModuleState:
    """Per-module static body vectors bs (n, 3), PRY angles theta (n, 3) and static rotations Rs (n, 3, 3).

    With the PRY update Rs = R_pry(theta) always; with the skew update Rs is carried as a matrix
    (theta keeps its start value and no longer describes Rs)."""

    bs: np.ndarray
    theta: np.ndarray
    Rs: np.ndarray
    rows: np.ndarray  # (n, 6) indices of module i's (bx, by, bz, pitch, roll, yaw) in the robot's parameter vector

    def vector(self) -> np.ndarray:
        """The robot parameter vector, each module's (bx, by, bz, pitch, roll, yaw) at its rows (a reconnected
        robot, `ga.reconfig.reorder`, keeps each module's rows while the chain order changes): valid for the
        PRY update."""
        a = np.empty(self.rows.size)
        a[self.rows.reshape(-1)] = np.concatenate([self.bs, self.theta], axis=1).reshape(-1)
        return a


def chain_of(robot: Robot) -> tuple[Chain, ModuleState]:
    """Structure and nominal module state of a serial robot built from PRY modules (seed 000 §3.2)."""
    for i, body in enumerate(robot.bodies):
        if body.conv is not PRY or body.parent != i - 1 or -1 in body.rows:
            raise ValueError(f"linear formulation needs a serial chain of PRY modules; body {i} ({body.name!r}) is "
                             f"{body.convention!r} with parent {body.parent}")
    if robot.gains is not None or robot.closure is not None or robot.tip not in (-1, len(robot.bodies) - 1):
        raise ValueError(f"robot {robot.name!r}: gains, closures or an inner tip are not part of the linear formulation")
    base_R = np.eye(3) if robot.base is None else np.asarray(robot.base.R, float)
    base_p = np.zeros(3) if robot.base is None else np.asarray(robot.base.p, float)
    chain = Chain(tuple(b.kind for b in robot.bodies), tuple(tuple(b.inputs) for b in robot.bodies), base_R, base_p)
    index = np.array([b.rows for b in robot.bodies])
    if sorted(index.reshape(-1)) != list(range(robot.n_params)):
        raise ValueError(f"robot {robot.name!r}: the modules' rows must cover the {robot.n_params} parameters once each")
    rows = np.asarray(robot.nominal_np)[index]
    theta = rows[:, 3:6]
    return chain, ModuleState(rows[:, 0:3].copy(), theta.copy(), np.asarray(jax.vmap(pry_to_matrix)(jnp.asarray(theta))),
                              index)


def tip_pose(chain: Chain, bs, Rs, q, post=None):
    """Tip (R, p) of one configuration: R_0i = R_0,i-1 Rs_i Rm_i, p = b0 + sum_i R_0i (bs_i + bm_i) (eq 3.43).

    Rs may be any 3x3 matrices (the skew update makes them non-orthogonal); post (n, 3, 3), if
    given, multiplies each module's frame after the joint motion (R_0i <- R_0i post_i)."""
    R, p = jnp.asarray(chain.base_R), jnp.asarray(chain.base_p)
    for i, (kind, inp) in enumerate(zip(chain.kinds, chain.inputs)):
        Rm, bm = pry_motion(kind, q[jnp.array(inp)] if inp else jnp.zeros(0))
        R = R @ Rs[i] @ Rm
        if post is not None:
            R = R @ post[i]
        p = p + R @ (bs[i] + bm)
    return R, p


def apply_increment(state_bs, state_theta, state_Rs, dg, update: str):
    """Module state after the increments dg (n, 6): bs + d (eq 4.28) and R_pry(theta + d) (eq 4.29) or Rs (I + skew d) (eq 4.30)."""
    bs = state_bs + dg[:, 0:3]
    if update == "pry":
        theta = state_theta + dg[:, 3:6]
        return bs, theta, jax.vmap(pry_to_matrix)(theta)
    if update == "skew":
        return bs, state_theta, state_Rs @ (jnp.eye(3) + jax.vmap(skew)(dg[:, 3:6]))
    raise ValueError(f"unknown update {update!r}; expected 'pry' (eq 4.29) or 'skew' (eq 4.30)")


def phi(theta):
    """Phi of eq 4.25: angular velocity (global) = Phi(theta) d(theta)/dt for R = Rx Ry Rz."""
    sx, cx, sy, cy = jnp.sin(theta[0]), jnp.cos(theta[0]), jnp.sin(theta[1]), jnp.cos(theta[1])
    z, o = jnp.zeros_like(sx), jnp.ones_like(sx)
    return jnp.stack([jnp.stack([o, z, sy]), jnp.stack([z, cx, -sx * cy]), jnp.stack([z, sx, cx * cy])])


def orientation_error_vect(Rm, Rn):
    """Delta beta = vect((R_m - R_n) R_n^T) (eq 4.19-4.20)."""
    return vect((Rm - Rn) @ Rn.T)


def orientation_error_pry(Rm, Rn, inverse: str = "atan2"):
    """Delta beta = Phi(theta_n) (theta_m - theta_n) with theta = f^-1(R) (eq 4.21-4.25); f^-1 of eq
    3.19 ("atan2", the Bai-Teo form), 3.18 ("acos") or 3.20-3.21 ("safe")."""
    f = INVERSES[inverse]
    th_n = f(Rn)
    return phi(th_n) @ (f(Rm) - th_n)


@functools.partial(jax.jit, static_argnames=("chain", "scheme", "error", "inverse"))
def pose_errors(chain: Chain, bs, Rs, Q, Rm, pm, *, scheme: str, error: str, inverse: str = "atan2"):
    """Stacked Delta X (m * rows,) and the (position, orientation) parts (m, 3) of measured minus model."""
    Rn, pn = jax.vmap(lambda q: tip_pose(chain, bs, Rs, q))(Q)
    dp = pm - pn
    if error == "vect":
        db = jax.vmap(orientation_error_vect)(Rm, Rn)
    else:
        db = jax.vmap(lambda a, b: orientation_error_pry(a, b, inverse))(Rm, Rn)
    dX = dp if scheme == "position" else jnp.concatenate([dp, db], axis=1)
    return dX.reshape(-1), dp, db


@functools.partial(jax.jit, static_argnames=("chain", "scheme", "update", "axes"))
def error_jacobian(chain: Chain, bs, theta, Rs, Q, *, scheme: str, update: str, axes: str = "static"):
    """J = d(tip position [, orientation]) / d(Delta g) at Delta g = 0 (eq 4.3-4.6) by forward-mode
    autodiff; orientation rows linearise vect(R(Delta g) R_n^T), the angular error of eq 4.19.

    axes "static": the rotation increments are those of the update (eq 4.29 or 4.30), so the step
    is Newton's; "moving": small rotations about the axes x_i, y_i, z_i of module i after its joint
    motion, the seed's geometric Jacobian (eq 4.3b), while the update still applies them to R_s."""
    n = bs.shape[0]
    Rn = jax.vmap(lambda q: tip_pose(chain, bs, Rs, q)[0])(Q)

    def model(dg):
        dg = dg.reshape(n, 6)
        if axes == "moving":
            b2, R2, post = bs + dg[:, 0:3], Rs, jnp.eye(3) + jax.vmap(skew)(dg[:, 3:6])
        else:
            (b2, _, R2), post = apply_increment(bs, theta, Rs, dg, update), None
        R, p = jax.vmap(lambda q: tip_pose(chain, b2, R2, q, post))(Q)
        if scheme == "position":
            return p.reshape(-1)
        ang = jax.vmap(lambda Ra, Rb: vect(Ra @ Rb.T))(R, Rn)
        return jnp.concatenate([p, ang], axis=1).reshape(-1)

    return jax.jacfwd(model)(jnp.zeros(6 * n))


def pseudo_inverse_step(J, dX):
    """Delta g = J^+ Delta X: J^T (J J^T)^-1 Delta X when under-determined (eq 4.26), (J^T J)^-1 J^T Delta X
    when over-determined (eq 4.27); by SVD (minimum norm) so a rank-deficient J is handled as well."""
    return np.linalg.lstsq(np.asarray(J), np.asarray(dX), rcond=None)[0]


def orthogonality(Rs) -> float:
    """max_i ||Rs_i^T Rs_i - I||_F: 0 for rotation matrices."""
    Rs = np.asarray(Rs)
    return float(np.max(np.linalg.norm(np.swapaxes(Rs, 1, 2) @ Rs - np.eye(3), axis=(1, 2))))


@dataclasses.dataclass(frozen=True)
class LinearResult:
    """Outcome of `linear_calibrate`: final module state, per-iteration history (entry 0 = before any update)."""

    state: ModuleState
    scheme: str
    error: str
    update: str
    rmspe: np.ndarray
    rmsoe: np.ndarray  # NaN throughout when no rotations were measured (position scheme with R_meas=None)
    rmse: np.ndarray
    orthogonality: np.ndarray
    condition: np.ndarray  # s_1 / s_r of J at each iteration, over the r singular values the pseudo-inverse uses
    rank: np.ndarray  # r: singular values above eps * max(J.shape) * s_1 (numpy's lstsq cutoff)
    iterations: int
    converged: bool

    @property
    def a(self) -> np.ndarray:
        """Robot parameter vector (PRY update only: the skew update has no PRY angles)."""
        if self.update != "pry":
            raise ValueError("the skew update (eq 4.30) carries Rs as matrices: no PRY parameter vector")
        return self.state.vector()


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.asarray(x) ** 2)))


def linear_calibrate(robot: Robot, Q, R_meas, p_meas, scheme: str = "position", category: int | None = None,
                     error: str = "vect", update: str = "pry", inverse: str = "atan2", axes: str = "static",
                     tol: float = 1e-6, max_iter: int = 20, angle_scale: float = 1.0) -> LinearResult:
    """The iterative linear calibration of Figure 4.1 from m measured tip poses.

    Q (m, n_inputs) joint values; R_meas (m, 3, 3) (may be None for the position scheme) and p_meas
    (m, 3) measured tip poses. scheme "position" (eq 4.5) or "pose" (eq 4.2); category 1-4 of
    Table 4.1 sets (error, update), otherwise they are given directly; inverse: the PRY inversion
    used by the PRY-difference error; axes: "static" (J of the update's own increments) or "moving"
    (the seed's eq 4.3b, see `error_jacobian`). Stops when the RMSE of the scheme's error vector <= tol.
    angle_scale: the unit, in rad, in which the pseudo-inverse's minimum-norm step measures the rotation
    increments (pi/180: degrees); where J is rank-deficient (one pose) it decides how a correction is shared
    between body vectors and angles: dg = D pinv(J D) Delta X with D = diag(1, 1, 1, s, s, s) per module."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}; expected one of {SCHEMES}")
    if category is not None:
        if category not in CATEGORIES:
            raise ValueError(f"category must be one of {sorted(CATEGORIES)} (Table 4.1), got {category}")
        error, update = CATEGORIES[category]
    if error not in ("vect", "pry") or update not in ("pry", "skew") or inverse not in INVERSES or axes not in ("static", "moving"):
        raise ValueError(f"error must be 'vect'/'pry', update 'pry'/'skew', inverse one of {sorted(INVERSES)}, axes "
                         f"'static'/'moving'; got {error!r}, {update!r}, {inverse!r}, {axes!r}")
    chain, st = chain_of(robot)
    Q = np.atleast_2d(np.asarray(Q, float))
    p_meas = np.asarray(p_meas, float).reshape(-1, 3)
    rotations_measured = R_meas is not None
    if not rotations_measured:
        if scheme == "pose":
            raise ValueError("the pose scheme needs measured rotations R_meas (m, 3, 3)")
        R_meas = np.broadcast_to(np.eye(3), (len(Q), 3, 3))  # placeholder: the position scheme never reads it
    R_meas = np.asarray(R_meas, float).reshape(-1, 3, 3)
    if not (len(Q) == len(p_meas) == len(R_meas)) or Q.shape[1] != robot.n_inputs:
        raise ValueError(f"Q {Q.shape}, R_meas {R_meas.shape}, p_meas {p_meas.shape}: need m joint vectors of "
                         f"{robot.n_inputs} and m measured poses")
    bs, theta, Rs = (jnp.asarray(v) for v in (st.bs, st.theta, st.Rs))
    Qj, Rmj, pmj = jnp.asarray(Q), jnp.asarray(R_meas), jnp.asarray(p_meas)
    hist = {"rmspe": [], "rmsoe": [], "rmse": [], "orth": [], "cond": [], "rank": []}
    converged, it = False, 0
    for it in range(max_iter + 1):
        dX, dp, db = pose_errors(chain, bs, Rs, Qj, Rmj, pmj, scheme=scheme, error=error, inverse=inverse)
        hist["rmspe"].append(_rms(dp))
        hist["rmsoe"].append(_rms(db) if rotations_measured else float("nan"))
        hist["rmse"].append(_rms(dX))
        hist["orth"].append(orthogonality(Rs))
        if not np.isfinite(hist["rmse"][-1]):
            break
        if hist["rmse"][-1] <= tol:
            converged = True
            break
        if it == max_iter:
            break
        J = np.asarray(error_jacobian(chain, bs, theta, Rs, Qj, scheme=scheme, update=update, axes=axes))
        sv = np.linalg.svd(J, compute_uv=False)
        rank = int(np.sum(sv > np.finfo(float).eps * max(J.shape) * sv[0]))
        hist["rank"].append(rank)
        hist["cond"].append(float(sv[0] / sv[rank - 1]))
        D = np.tile(np.array([1.0, 1.0, 1.0, angle_scale, angle_scale, angle_scale]), J.shape[1] // 6)
        dg = (D * pseudo_inverse_step(J * D, dX)).reshape(-1, 6)
        bs, theta, Rs = apply_increment(bs, theta, Rs, jnp.asarray(dg), update)
    state = ModuleState(np.asarray(bs), np.asarray(theta), np.asarray(Rs), st.rows)
    return LinearResult(state, scheme, error, update, np.array(hist["rmspe"]), np.array(hist["rmsoe"]), np.array(hist["rmse"]),
                        np.array(hist["orth"]), np.array(hist["cond"]), np.array(hist["rank"]), it, converged)
