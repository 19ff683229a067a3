"""The physics skid-steer plant: four wheels, two velocity-controlled motors, slip-dependent friction.

This robot is deliberately outside the nominal dynamic unicycle's class, so the nominal model
leaves terrain-dependent residuals for the GP to learn:

- command mapping: wheel-speed setpoints `(v_ref -+ omega_ref * track_multiplier * track / 2) / R`,
  each clamped to `max_speed / R` (so fast turns saturate, as on the real base), smoothed by the
  motor drivers' first-order setpoint lag;
- per side a PI velocity loop with conditional-integration anti-windup, and a torque limit that
  falls linearly with wheel speed (DC-motor torque-speed line; full torque when braking);
- per wheel a smooth anisotropic Coulomb law on the combined slip velocity
  `F = mu N tanh(|s|) s/|s|`, `s = ((R w - vx) / s_long, vy / s_lat)`, so the skid moment that
  resists turning emerges from the lateral wheel forces and weakens while wheels spin;
- rolling resistance `rolling N` plus speed-proportional drag at each contact point;
- planar rigid body `m (du/dt - vy r) = sum Fx`, `m (dvy/dt + u r) = sum Fy`,
  `Iz dr/dt = sum (x_i Fy_i - y_i Fx_i)`, integrated by semi-implicit Euler at a fixed step.

State returned by `step`: `[X, Y, yaw, v, omega]` with v the body forward velocity (true values);
`measure()` adds seeded Gaussian sensor noise. The lateral velocity is internal (`lateral_velocity`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gpmppi.plant.terrains import RobotParams, TerrainParams, TerrainSet

GRAVITY = 9.81

# Packed parameter vector (one float64 array so the kernel takes a single argument).
P_MASS, P_IZ, P_HALF_TRACK, P_HALF_BASE, P_R, P_J = 0, 1, 2, 3, 4, 5
P_WMAX, P_MAP_HALF_TRACK, P_KP, P_KI, P_TMAX, P_WNL, P_DAMP = 6, 7, 8, 9, 10, 11, 12
P_MU_X, P_MU_Y, P_S_X, P_S_Y, P_ROLL, P_DRAG, P_H, P_TAU_REF = 13, 14, 15, 16, 17, 18, 19, 20
N_PARAMS = 21

# Internal state: pose, body velocities, side wheel speeds, PI integrator states, filtered wheel references.
Z_X, Z_Y, Z_YAW, Z_U, Z_VY, Z_R, Z_WL, Z_WR, Z_IL, Z_IR, Z_FL, Z_FR = range(12)
N_INTERNAL = 12

ROLLING_SMOOTHING = 0.02  # [m/s] tanh scale that makes rolling resistance vanish smoothly at rest


def pack_params(robot: RobotParams, terrain: TerrainParams) -> np.ndarray:
    """The kernel's parameter vector for this robot on this terrain."""
    p = np.zeros(N_PARAMS)
    p[P_MASS] = robot.mass
    p[P_IZ] = robot.yaw_inertia
    p[P_HALF_TRACK] = 0.5 * robot.track
    p[P_HALF_BASE] = 0.5 * robot.wheelbase
    p[P_R] = robot.wheel_radius
    p[P_J] = robot.side_inertia
    p[P_WMAX] = robot.max_speed / robot.wheel_radius
    p[P_MAP_HALF_TRACK] = 0.5 * robot.track * robot.track_multiplier
    p[P_KP] = robot.motor_kp
    p[P_KI] = robot.motor_ki
    p[P_TMAX] = robot.motor_torque_max
    p[P_WNL] = robot.motor_noload_speed / robot.wheel_radius
    p[P_DAMP] = robot.drivetrain_damping
    p[P_MU_X] = terrain.mu_long
    p[P_MU_Y] = terrain.mu_lat
    p[P_S_X] = terrain.slip_scale_long
    p[P_S_Y] = terrain.slip_scale_lat
    p[P_ROLL] = terrain.rolling
    p[P_DRAG] = terrain.drag
    p[P_H] = robot.internal_dt
    p[P_TAU_REF] = robot.motor_ref_time_constant
    return p


@njit(cache=True, inline="always")
def _motor_torque(p: np.ndarray, w_ref: float, w: float, integ: float) -> tuple[float, bool]:
    """PI torque clamped to the torque-speed envelope; also whether the clamp was active."""
    tau = p[P_KP] * (w_ref - w) + p[P_KI] * integ
    speed_frac = min(abs(w) / p[P_WNL], 1.0)
    motoring_lim = p[P_TMAX] * (1.0 - speed_frac)
    if w >= 0.0:
        hi, lo = motoring_lim, -p[P_TMAX]
    else:
        hi, lo = p[P_TMAX], -motoring_lim
    if tau > hi:
        return hi, True
    if tau < lo:
        return lo, True
    return tau, False


@njit(cache=True)
def simulate(p: np.ndarray, z: np.ndarray, v_ref: float, w_ref: float, n_steps: int) -> None:
    """Advance the internal state `z` in place by `n_steps` fixed steps under a constant command."""
    m, iz, c, a, rad, jw = p[P_MASS], p[P_IZ], p[P_HALF_TRACK], p[P_HALF_BASE], p[P_R], p[P_J]
    h = p[P_H]
    normal = m * GRAVITY / 4.0
    fx_max = p[P_MU_X] * normal
    fy_max = p[P_MU_Y] * normal
    roll = p[P_ROLL] * normal
    wmax = p[P_WMAX]
    wr_cmd = min(max((v_ref + w_ref * p[P_MAP_HALF_TRACK]) / rad, -wmax), wmax)
    wl_cmd = min(max((v_ref - w_ref * p[P_MAP_HALF_TRACK]) / rad, -wmax), wmax)
    ref_gain = h / (p[P_TAU_REF] + h)  # implicit-Euler first-order lag of the drivers' setpoint
    wheel_x = (a, -a, a, -a)
    wheel_y = (c, c, -c, -c)  # wheels 0, 1 on the left, 2, 3 on the right
    for _ in range(n_steps):
        z[Z_FL] += ref_gain * (wl_cmd - z[Z_FL])
        z[Z_FR] += ref_gain * (wr_cmd - z[Z_FR])
        wl_ref, wr_ref = z[Z_FL], z[Z_FR]
        u, vy, r = z[Z_U], z[Z_VY], z[Z_R]
        sum_fx = 0.0
        sum_fy = 0.0
        moment = 0.0
        side_fx_l = 0.0
        side_fx_r = 0.0
        for i in range(4):
            xi, yi = wheel_x[i], wheel_y[i]
            vx_i = u - r * yi
            vy_i = vy + r * xi
            w_side = z[Z_WL] if i < 2 else z[Z_WR]
            sx = (rad * w_side - vx_i) / p[P_S_X]
            sy = vy_i / p[P_S_Y]
            mag = math.sqrt(sx * sx + sy * sy)
            gain = math.tanh(mag) / mag if mag > 1e-9 else 1.0
            fx = fx_max * gain * sx
            fy = -fy_max * gain * sy
            resist = -(roll * math.tanh(vx_i / ROLLING_SMOOTHING) + p[P_DRAG] * vx_i)
            sum_fx += fx + resist
            sum_fy += fy
            moment += xi * fy - yi * (fx + resist)
            if i < 2:
                side_fx_l += fx
            else:
                side_fx_r += fx
        tau_l, sat_l = _motor_torque(p, wl_ref, z[Z_WL], z[Z_IL])
        tau_r, sat_r = _motor_torque(p, wr_ref, z[Z_WR], z[Z_IR])
        # conditional integration: freeze the integrator while the torque is clamped
        if not sat_l:
            z[Z_IL] += (wl_ref - z[Z_WL]) * h
        if not sat_r:
            z[Z_IR] += (wr_ref - z[Z_WR]) * h
        z[Z_WL] += h * (tau_l - rad * side_fx_l - p[P_DAMP] * z[Z_WL]) / jw
        z[Z_WR] += h * (tau_r - rad * side_fx_r - p[P_DAMP] * z[Z_WR]) / jw
        u_new = u + h * (sum_fx / m + vy * r)
        vy_new = vy + h * (sum_fy / m - u * r)
        r_new = r + h * moment / iz
        z[Z_U], z[Z_VY], z[Z_R] = u_new, vy_new, r_new
        # semi-implicit: the pose moves with the updated velocities
        cy, sy_ = math.cos(z[Z_YAW]), math.sin(z[Z_YAW])
        z[Z_X] += h * (u_new * cy - vy_new * sy_)
        z[Z_Y] += h * (u_new * sy_ + vy_new * cy)
        z[Z_YAW] += h * r_new


def _wrap(a: float) -> float:
    w = (a + math.pi) % (2.0 * math.pi) - math.pi
    return math.pi if w == -math.pi else w


class PhysicsPlant:
    """The default simulated robot; implements the Plant protocol (`reset`, `step`, `measure`, `set_terrain`)."""

    def __init__(self, terrains: TerrainSet, terrain: str, seed: int = 0, noise: bool = True) -> None:
        self.terrains = terrains
        self.robot = terrains.robot
        self.dt = float(self.robot.internal_dt)
        self.noise = noise
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        self._noise_std = np.array(
            [self.robot.noise_pos, self.robot.noise_pos, self.robot.noise_yaw, self.robot.noise_v,
             self.robot.noise_omega]
        )
        self.terrain = ""
        self._params = np.zeros(N_PARAMS)
        self.set_terrain(terrain)
        self._z = np.zeros(N_INTERNAL)
        self.time = 0.0

    def set_terrain(self, name: str) -> None:
        """Switch the ground under the robot (the state carries over)."""
        self._params = pack_params(self.robot, self.terrains.get(name))
        self.terrain = name

    def reset(self, state: np.ndarray) -> None:
        """Place the robot at `[X, Y, yaw, v, omega]` with no lateral slip, wheels rolling, integrators at zero."""
        s = np.asarray(state, dtype=float)
        if s.shape != (5,) or not np.all(np.isfinite(s)):
            raise ValueError(f"reset state must be 5 finite numbers [X, Y, yaw, v, omega], got {state!r}")
        z = np.zeros(N_INTERNAL)
        z[Z_X], z[Z_Y], z[Z_YAW], z[Z_U], z[Z_R] = s
        c = 0.5 * self.robot.track
        z[Z_WL] = (s[3] - s[4] * c) / self.robot.wheel_radius
        z[Z_WR] = (s[3] + s[4] * c) / self.robot.wheel_radius
        z[Z_FL], z[Z_FR] = z[Z_WL], z[Z_WR]
        self._z = z
        self._rng = np.random.default_rng(self.seed)
        self.time = 0.0

    def step(self, command: np.ndarray, duration: float) -> np.ndarray:
        """Apply `[v_ref, omega_ref]` for `duration` seconds (rounded to whole internal steps); the true state."""
        cmd = np.asarray(command, dtype=float)
        if cmd.shape != (2,) or not np.all(np.isfinite(cmd)):
            raise ValueError(f"command must be 2 finite numbers [v_ref, omega_ref], got {command!r}")
        if not duration > 0.0:
            raise ValueError(f"duration must be positive, got {duration}")
        n = max(1, int(round(duration / self.dt)))
        simulate(self._params, self._z, float(cmd[0]), float(cmd[1]), n)
        if not np.all(np.isfinite(self._z)):
            raise FloatingPointError(f"physics plant diverged on terrain {self.terrain!r}; lower internal_dt")
        self.time += n * self.dt
        return self.state()

    def state(self) -> np.ndarray:
        """True `[X, Y, yaw, v, omega]` (yaw wrapped)."""
        z = self._z
        return np.array([z[Z_X], z[Z_Y], _wrap(z[Z_YAW]), z[Z_U], z[Z_R]])

    def measure(self) -> np.ndarray:
        """The state with seeded Gaussian sensor noise (no noise when constructed with noise=False)."""
        s = self.state()
        if self.noise:
            s = s + self._rng.normal(0.0, 1.0, 5) * self._noise_std
            s[2] = _wrap(s[2])
        return s

    @property
    def lateral_velocity(self) -> float:
        """True body-frame lateral velocity [m/s] (skid), for analysis."""
        return float(self._z[Z_VY])

    @property
    def wheel_speeds(self) -> np.ndarray:
        """True (left, right) side wheel speeds [rad/s]."""
        return self._z[[Z_WL, Z_WR]].copy()
