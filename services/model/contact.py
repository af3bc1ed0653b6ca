"""Contact detection from the arm's own joint torques: the generalized-momentum observer and the thresholds it is
judged against (pure: no zenoh, no clock, no locks; one per loop).

The observer (De Luca and Mattone, ICRA 2005; Haddadin, De Luca and Albu-Schäffer, "Robot collisions: a survey on
detection, isolation, and identification", T-RO 33(6) 2017, §IV-C, eqs. 26-28) watches the generalized momentum
p = M(q)q̇, whose rate the rigid-body dynamics give as ṗ = τ + Cᵀ(q, q̇)q̇ − g(q) + τ_ext. Its residual

    r(t) = K_O (p(t) − p(0) − ∫₀ᵗ (τ + Cᵀq̇ − g + r) ds)

follows τ_ext through a first-order filter of gain K_O (ṙ = K_O (τ_ext − r)), from the measured joint torques, angles
and speeds alone: no joint acceleration, no inverse of M. τ here is what the joints' torque sensors read less the
description's viscous friction (D q̇): the emulated sensors read the motor's torque ahead of the joint's friction
(docs/contact.md says why that departs from a real JACO-2, whose sensor sits at the output).

Isolation (the same survey, §V): a force on link k gives τ_ext = J_kᵀ F, whose entries beyond joint k are zero, so
the contacted link is the most distal joint whose residual leaves its band.

The thresholds (:func:`contact_thresholds`) are what a residual may show with no contact: the sensor's drift (its
data sheet), its noise through the observer's filter, what the description's uncertainty (the hand's mass and
inertia, a payload's) makes of the arm's dynamics at any configuration and speed within its limits, and the joint
friction the description leaves out; docs/contact.md derives each.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Optional

import numpy as np
import pinocchio as pin

from services.model.arm import ArmDescription
from services.model.dynamics import DynamicsModel

#: the thresholds stand this many standard deviations of the filtered sensor noise above the bias and model error:
#: a Gaussian's two-sided tail beyond 6σ is 2·10⁻⁹ per sample and joint, so a six-joint arm's residuals at 500 Hz,
#: correlated over the filter's few samples, leave their band by noise about once in several years (mfvs's choice;
#: libfranka's and KUKA's thresholds are set by hand, 12-20 N·m in libfranka's examples)
NOISE_SIGMAS = 6.0
#: the observer's gain K_O as a multiple of the sample rate: K_O·Δt = 0.5, a time constant of two samples (at
#: 500 Hz 4 ms, at 100 Hz 20 ms). K_O·Δt = 1 would follow τ_ext in one sample with the sensor's whole noise;
#: 0.5 passes half the noise's σ for a lag of one more sample (mfvs's choice, checked in docs/contact.md against
#: the issue's force-growth figure; the survey's examples run K_O of 25-250 s⁻¹)
GAIN_TIMES_PERIOD = 0.5
#: a gap between two samples longer than this many nominal periods restarts the observer (the integral of a
#: stale interval is not the arm's motion): a late host shows as restarts, counted, never as a residual
MAX_GAP_PERIODS = 4.0
#: configurations, speeds and accelerations drawn (seeded) to bound the model error over the arm's limits
MODEL_ERROR_SAMPLES = 4000


# ------------------------------------------------------------------------------------------------- the equations
def generalized_momentum(M: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """p = M(q)q̇ (T-RO 2017, eq. 26)."""
    return M @ dq


def generalized_momentum_by_rnea(inverse_dynamics_at_rest: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """p = M(q)q̇ from RNEA(q, 0, q̇) = M(q)q̇ + g(q) (the same momentum as :func:`generalized_momentum`)."""
    return inverse_dynamics_at_rest - gravity


def observer_input(tau: np.ndarray, coriolis_transpose_dq: np.ndarray, gravity: np.ndarray,
                   friction: np.ndarray) -> np.ndarray:
    """β = τ − D q̇ + Cᵀ(q, q̇)q̇ − g(q): the momentum's rate without the external torque (T-RO 2017, eq. 25, with the
    joint torque less the described viscous friction ``friction`` = D q̇)."""
    return tau - friction + coriolis_transpose_dq - gravity


def momentum_residual(gain: float, momentum: np.ndarray, initial_momentum: np.ndarray,
                      integral: np.ndarray) -> np.ndarray:
    """r = K_O (p − p(0) − ∫(β + r)) (T-RO 2017, eq. 27), the integral taken up to this sample."""
    return gain * (momentum - initial_momentum - integral)


def integrate_observer(integral: np.ndarray, previous_beta: np.ndarray, beta: np.ndarray, residual: np.ndarray,
                       dt: float) -> np.ndarray:
    """∫(β + r) one sample on: β by the trapezoid between the two samples (it moves with q and q̇ within a
    sample), r held at the previous sample's (the survey's discrete form, which keeps the observer explicit)."""
    return integral + (0.5 * (previous_beta + beta) + residual) * dt


def filtered_noise_sigma(sigma: np.ndarray, gain_times_period: float) -> np.ndarray:
    """The residual's standard deviation from white sensor noise σ: at rest the observer is
    r_k = (1 − a) r_{k−1} − a (n_{k−1} + n_k)/2 with a = K_O·Δt (the trapezoid averages two samples' noise), whose
    impulse response squared sums to 2/a, so its variance is (a²/4)·σ²·(2/a) = σ²·a/2."""
    return np.asarray(sigma, dtype=float) * math.sqrt(gain_times_period / 2.0)


def isolated_joint(residual: np.ndarray, threshold: np.ndarray) -> int:
    """The contacted link's joint (1-based; 0: none): the most distal joint whose residual leaves its band."""
    over = np.flatnonzero(np.abs(residual) > threshold)
    return int(over[-1]) + 1 if over.size else 0


# ------------------------------------------------------------------------------------------------- thresholds
@dataclass(frozen=True)
class Uncertainty:
    """What the description may get wrong: the hand's (last link's) mass and inertia by this fraction, and a
    payload in the hand up to ``payload_kg`` not declared to the model, at the end effector."""

    hand_mass_fraction: float = 0.4
    payload_kg: float = 0.0


@dataclass(frozen=True)
class ThresholdTerms:
    """Each term of a joint's threshold (N·m, one per joint), and their sum."""

    drift_nm: np.ndarray
    noise_nm: np.ndarray
    model_nm: np.ndarray
    friction_nm: np.ndarray

    @property
    def total_nm(self) -> np.ndarray:
        return self.drift_nm + self.noise_nm + self.model_nm + self.friction_nm


def contact_thresholds(arm: ArmDescription, uncertainty: Uncertainty = Uncertainty(),
                       gain_times_period: float = GAIN_TIMES_PERIOD) -> ThresholdTerms:
    """Each joint's threshold and its terms: the torque sensor's drift (data sheet, ±); :data:`NOISE_SIGMAS` of its
    noise (the sheet's precision as 2σ, the emulation's reading) through the observer's filter; the largest error the
    description's uncertainty makes of M q̈ + C q̇ + g over the arm's joint ranges, speeds and acceleration; and the
    Coulomb friction the description leaves out where an actuator's torque loop leaves some (torque mode)."""
    specs = [j.spec for j in arm.joints]
    drift = np.array([s.torque_sensor_drift_nm for s in specs])
    sigma = np.array([s.torque_sensor_precision_nm / 2.0 for s in specs])
    noise = NOISE_SIGMAS * filtered_noise_sigma(sigma, gain_times_period)
    model = model_error_bound(arm, uncertainty)
    friction = arm.torque_mode_friction_fraction * np.array([s.backdriving_torque_nm[0] for s in specs])
    return ThresholdTerms(drift_nm=drift, noise_nm=noise, model_nm=model, friction_nm=friction)


def perturbed_model(arm: ArmDescription, uncertainty: Uncertainty) -> "pin.Model":
    """The description's Pinocchio model with the hand heavier by the uncertainty's fraction and the payload at the
    end effector (what the arm may really be)."""
    model = DynamicsModel(arm, rotor_inertia=True).model
    hand = model.inertias[model.njoints - 1]
    scale = 1.0 + uncertainty.hand_mass_fraction
    model.inertias[model.njoints - 1] = pin.Inertia(hand.mass * scale, hand.lever, hand.inertia * scale)
    if uncertainty.payload_kg > 0.0:
        shared = arm.load_pinocchio()
        ee = shared.model.frames[shared.ee_frame_id]
        payload = pin.Inertia.FromSphere(uncertainty.payload_kg, 0.03)
        model.inertias[ee.parentJoint] = model.inertias[ee.parentJoint] + ee.placement.act(payload)
    return model


def model_error_bound(arm: ArmDescription, uncertainty: Uncertainty, samples: int = MODEL_ERROR_SAMPLES,
                      seed: int = 0) -> np.ndarray:
    """Per joint, the largest |τ_true − τ_model| of inverse dynamics (RNEA) between the perturbed model and the
    description, over seeded configurations within the joints' ranges, speeds up to their maxima and accelerations
    up to the arm's joint acceleration limit (cached per arm and uncertainty)."""
    return _model_error_bound(arm, uncertainty, samples, seed).copy()


@lru_cache(maxsize=16)
def _model_error_bound(arm: ArmDescription, uncertainty: Uncertainty, samples: int, seed: int) -> np.ndarray:
    nominal = DynamicsModel(arm, rotor_inertia=True).model
    true = perturbed_model(arm, uncertainty)
    nominal_data, true_data = nominal.createData(), true.createData()
    rng = np.random.default_rng(seed)
    lower, upper = arm.model_limits()
    lower = np.where(np.isfinite(lower), lower, -math.pi)
    upper = np.where(np.isfinite(upper), upper, math.pi)
    accel = math.radians(arm.joint_accel_dps2)
    worst = np.zeros(arm.n_joints)
    for _ in range(samples):
        q = rng.uniform(lower, upper)
        dq = rng.uniform(-1.0, 1.0, arm.n_joints) * arm.max_speed
        ddq = rng.uniform(-1.0, 1.0, arm.n_joints) * accel
        error = pin.rnea(true, true_data, q, dq, ddq) - pin.rnea(nominal, nominal_data, q, dq, ddq)
        worst = np.maximum(worst, np.abs(error))
    return worst


# ------------------------------------------------------------------------------------------------- the monitor
@dataclass(frozen=True)
class ContactSample:
    """What the monitor made of one reading: the residual (N·m per joint), its largest ratio to the threshold, and
    whether it leaves its band now (the joint named, 1-based; 0 none)."""

    residual: np.ndarray
    ratio: float
    joint: int

    @property
    def in_contact(self) -> bool:
        return self.joint > 0


class ContactMonitor:
    """The momentum observer on the description's M, C, g (Pinocchio, with the rotor inertia and viscous friction
    the emulated arm has), fed one joint reading at a time at the rate of its path (``period_s``: the bus cycle, or
    the DSP's 100 Hz), judged against :func:`contact_thresholds`. Not thread-safe: one per loop."""

    def __init__(self, arm: ArmDescription, period_s: float, uncertainty: Uncertainty = Uncertainty(),
                 gain_times_period: float = GAIN_TIMES_PERIOD) -> None:
        if not 0.0 < gain_times_period < 2.0:  # the discrete observer is stable for K_O·Δt in (0, 2)
            raise ValueError(f"gain_times_period {gain_times_period}: the observer needs it within (0, 2)")
        if not period_s > 0.0:
            raise ValueError(f"period_s {period_s}: must be positive")
        self.arm = arm
        self.period_s = period_s
        self.gain = gain_times_period / period_s
        self.terms = contact_thresholds(arm, uncertainty, gain_times_period)
        self.threshold = self.terms.total_nm
        self._dynamics = DynamicsModel(arm, rotor_inertia=True, friction=True)
        self._model, self._data = self._dynamics.model, self._dynamics.data
        self._damping = self._dynamics.friction
        self._zero = np.zeros(arm.n_joints)
        # the observer's state, set at its first reading (and after a gap): p(0), ∫(β + r), r, and β at the last
        # reading
        self._initial: Optional[np.ndarray] = None
        self._integral = self._residual = self._beta = np.zeros(arm.n_joints)
        self._last_stamp_s = 0.0
        #: the observer restarted after a gap (or a step back) in the readings' stamps
        self.restarts = 0
        #: samples taken
        self.samples = 0

    def update(self, q, dq, tau, stamp_s: float) -> ContactSample:
        """One reading (model units; its stamp on the arm's timeline, s)."""
        q, dq, tau = (np.asarray(v, dtype=float) for v in (q, dq, tau))
        model, data = self._model, self._data
        gravity = pin.computeGeneralizedGravity(model, data, q).copy()
        # p = M(q)q̇ as inverse dynamics at rest with q̇ for the acceleration (RNEA: M q̇ + g), which spares
        # building and symmetrising M: the same to 1e-15, a third of the reading's cost
        momentum = generalized_momentum_by_rnea(pin.rnea(model, data, q, self._zero, dq), gravity)
        coriolis = pin.computeCoriolisMatrix(model, data, q, dq)
        beta = observer_input(tau, coriolis.T @ dq, gravity, self._damping * dq)
        dt = stamp_s - self._last_stamp_s
        self._last_stamp_s = stamp_s
        if self._initial is not None and not 0.0 < dt <= MAX_GAP_PERIODS * self.period_s:
            self.restarts += 1
            self._initial = None
        if self._initial is None:
            self._initial = momentum
            self._integral = np.zeros(self.arm.n_joints)
            self._residual = np.zeros(self.arm.n_joints)
        else:
            self._integral = integrate_observer(self._integral, self._beta, beta, self._residual, dt)
            self._residual = momentum_residual(self.gain, momentum, self._initial, self._integral)
        self._beta = beta
        self.samples += 1
        # (each sample's residual is a new array: the sample may keep it)
        ratio = float((np.abs(self._residual) / self.threshold).max())
        return ContactSample(residual=self._residual, ratio=ratio,
                             joint=isolated_joint(self._residual, self.threshold) if ratio > 1.0 else 0)
