"""The error budget of an output edge pose (issues 11/12): a pose is output as `model` only where
its image pins it to the issue's 1 % of the distance / 2 deg.

* :func:`beyond_budget`: the pose's own uncertainty (its fit's covariance, ``sigmas`` x 1-sigma)
  beyond :class:`PoseBudget` (reason ``pose uncertain``);
* :func:`ambiguity`: a second healthy fit of the same image, from another start, beyond the budget
  from it (reason ``ambiguous``);
* :class:`ModelDistance`: the camera-to-model distance that the budget is relative to.

Used by :class:`mst.pipeline.tracking.session.TrackingSession` on the pose a frame settled on, after
every other test. Frames: ``T_cam_model`` (ViSP cMo), twists ``(v m, w rad)`` in the camera frame.
Metres, degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mst.core.poses import inv_T, matmul_exact, pose_error, se3_exp
from mst.pipeline.tracking.exact import centre, eigh, eigvalsh, norm3

#: the reason (``traj.csv``) of an edge pose refused by the error budget: its own uncertainty beyond
#: it, or two fits of the image beyond it apart
REASON_UNCERTAIN = "pose uncertain"
REASON_AMBIGUOUS = "ambiguous"


@dataclass(frozen=True)
class PoseBudget:
    """The error budget of an output pose: its ``sigmas`` x 1-sigma bound within ``rel`` x its
    distance to the model and ``deg`` degrees (the drift budget's values, ``slam.drift_*``)."""

    rel: float = 0.01
    deg: float = 2.0
    sigmas: float = 2.0


#: an edge pose is fitted again from the motion prediction (:func:`ambiguity`) when it
#: lies more than this x the budget from it: a cost bound (one extra fit on those frames only); measured
#: centre gaps pose-prediction, % of the distance: real teabox median 0.24 (default) / 0.44 (edges
#: only), UAV passes 0.06-0.15, `carried` 0.16 (up to 3.3 while the hand accelerates the object)
AMBIGUITY_SCREEN = 0.5

#: after a refused frame the next edge pose is also fitted from this many sigma either side along its
#: covariance's weakest direction (a unique minimum pulls both back; Rotterdam FPV frame 6, 2.9 % off
#: after the refused frame 5: 1.7-2.1 % away; correct frames after a refusal 0.04-0.23 %)
BASIN_SIGMAS = 3.0


def centre_gap(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Distance (m) between the camera centres of two ``T_cam_model`` poses."""
    return norm3(centre(T_a) - centre(T_b))


class ModelDistance:
    """``distance(T_cam_model)``: a lower bound (m) on the distance from the camera centre to the
    nearest model vertex, within 5 % of it. The distance is 1-Lipschitz in the centre c, so the
    last exact value d0 at c0 gives ``d0 - |c - c0|``; it is recomputed (all vertices) once the
    centre has moved more than 5 % of d0."""

    def __init__(self, vertices: np.ndarray):
        self.V = np.asarray(vertices, float)
        self.c0: np.ndarray | None = None
        self.d0 = float("inf")

    def __call__(self, T_cam_model: np.ndarray) -> float:
        c = centre(T_cam_model)
        if self.c0 is not None:
            moved = norm3(c - self.c0)
            if moved <= 0.05 * self.d0:
                return self.d0 - moved
        self.c0 = c
        self.d0 = float(np.sqrt(((self.V - c) ** 2).sum(1).min())) if len(self.V) else float("inf")
        return self.d0


#: after a frame refused as uncertain, output resumes only once a pose's bound is within this
#: fraction of the budget (hysteresis: the bound is itself an estimate, optimistic 2-2.4x on the
#: demo's UAV pass; while the model leaves the view the bound grows and a frame that dips back just
#: under the line is the least trustworthy: that pass's frame 83, after frames 81-82 refused at
#: 1.0 / 1.3 %, passed at 2 sigma < 1 % and was 1.43 % off)
RETURN_FRACTION = 0.5

#: ... or once this many frames in a row lie within the full budget with the view holding still
#: (each of them refused by the return fraction, the last one output): a bound that stays under the
#: line in a steady view is no dip. Without it a view whose honest bound stays between half and all
#: of the budget was refused for good: the Rotterdam 250 m survey band, after one frame at 2 sigma =
#: 1.0 %, refused the next 27 frames at 0.6-1.0 % (never under 0.5 %) while its err / sigma is 1.2
#: over the pass and 0.99 at the true poses (the bound is honest there and the image gives no more:
#: tests/test_track_uav.py)
RETURN_STEADY_FRAMES = 3

#: the view holds still: the frame's visible edge samples (before the ``max_samples`` cap) within this fraction of the previous
#: frame's. Where the model enters or leaves the view the bound is optimistic (above): the demo's UAV
#: return after the turn grew 15 / 10 / 6 / 3 % a frame (frames 162-165, 2 sigma 0.9-0.7 % while
#: 164 was 0.88 % off, 2.5 sigma), the 250 m band's turn 2-10 % (frame 73, 2 sigma 0.9 %, 0.99 % off);
#: its steady flight after the turn 0-4 %
RETURN_STEADY_VIEW = 0.05


def positive_definite(C: np.ndarray) -> bool:
    """Whether the symmetric 6x6 ``C`` is a covariance: finite, positive variances, its correlation
    matrix's smallest eigenvalue above 1e-12 (the test ``traj.cov.csv`` writes a covariance by)."""
    if not np.isfinite(C).all() or not (np.diag(C) > 0).all():
        return False
    d = 1.0 / np.sqrt(np.diag(C))
    return bool(eigvalsh(C * d[:, None] * d[None, :]).min() > 1e-12)


def beyond_budget(b: PoseBudget, cov: np.ndarray | None, T: np.ndarray | None, distance_m,
                  fraction: float = 1.0) -> str:
    """Why an edge pose's own uncertainty exceeds the error budget ('' when it does not, or
    without a budget): its ``sigmas`` x 1-sigma camera-centre bound (from the fit's 6x6
    covariance, the trace of its position block) beyond ``rel`` x the distance to the model, or
    its rotation bound beyond ``deg``. The same budget as a map pose's (the drift budget,
    ``slam.drift_budget_rel`` / ``_deg`` / ``drift_sigmas``): a pose is output only where its
    image pins it to the budget (Delft at 250 m, 640x480: 1-sigma 0.6-1.4 % of the distance,
    errors 0.3-3 %); a fit without a finite covariance is beyond it."""
    if cov is None or T is None:
        return ""
    if not np.isfinite(cov).all():  # a fit whose information cannot be inverted pins nothing
        return f"{REASON_UNCERTAIN}: no finite covariance (a degenerate fit)"
    if not positive_definite(0.5 * (cov + cov.T)):
        # an indefinite inverse (a direction the fit does not pin, lost in rounding) bounds nothing:
        # its trace could pass the budget, and the pose was output as `model` with no covariance
        # written (Rotterdam 120 m survey, 640x480, seed 1, frame 81)
        return f"{REASON_UNCERTAIN}: covariance not positive definite (a degenerate fit)"
    pos = b.sigmas * float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0)))
    rot = b.sigmas * float(np.degrees(np.sqrt(max(eigvalsh(0.5 * (cov[3:, 3:] + cov[3:, 3:].T)).max(), 0.0))))
    d = distance_m(T)
    if pos <= fraction * b.rel * d and rot <= fraction * b.deg:
        return ""
    after = f", {fraction:g} x after a refusal" if fraction != 1.0 else ""
    return (f"{REASON_UNCERTAIN}: {b.sigmas:g} sigma = {pos / d:.1%} of the model distance, {rot:.2f} deg "
            f"(budget {b.rel:.0%}, {b.deg:g} deg{after})")


#: a refit beyond the budget whose calibrated health score exceeds the pose's by more than this is
#: the better minimum of the image and replaces the pose (one z unit of the worst health signal:
#: the score is 1 - z / 4): two minima are ambiguous only where the evidence cannot choose.
#: Measured on the real teabox, edges only at half frame rate, frame 22: the first fit scored 0.66,
#: 3.7 mm from the edges+KLT run; the fit from the prediction scored 0.96, 1.9 mm from it
SCORE_MARGIN = 0.25


def ambiguity(b: PoseBudget, fr, d: float, T_cv: np.ndarray | None, after_refusal: bool, refit, align=None):
    """Why the healthy edge pose ``fr`` is ambiguous ('' when it is not); ``d`` its model distance (m),
    ``refit(T_start) -> FrameResult`` a judged fit of the same image from another start. With
    ``fr`` far from the motion prediction ``T_cv`` (the constant-velocity pose of the last two
    model frames, beyond ``AMBIGUITY_SCREEN`` x the budget) the image is fitted again from it;
    ``after_refusal`` (the last frame refused) also from +-``BASIN_SIGMAS`` along the fit's
    weakest direction. Two healthy fits of one image more than the
    budget apart (``b.rel`` x the distance, or ``b.deg``): at least one of them is more than half
    the budget off and the image cannot tell which. A real acceleration (the object carried by hand) refits to the same pose.
    Measured, the fit from the prediction against the pose, % of the distance: Rotterdam FPV
    frame 5 (2.1 % off) 1.74; correct frames 0.01-0.34 (real teabox edges only, `carried`).
    ``align(T_ref, T)`` maps ``T`` onto ``T_ref`` modulo a symmetry of the model (a body of
    revolution's turn about its axis is no difference of the image); identity when None.
    Returns ``(why, better)``: ``better`` a refit beyond the budget whose health score is higher
    than ``fr``'s by ``SCORE_MARGIN`` (the frame takes it; ``why`` empty), else None."""
    T = fr.T_cam_model
    sym = align if align is not None else (lambda T_ref, T_b: T_b)
    starts = []
    if T_cv is not None and centre_gap(T, sym(T, T_cv)) > AMBIGUITY_SCREEN * b.rel * d:
        starts.append(("the motion prediction", T_cv))
    if after_refusal and fr.cov is not None and np.isfinite(fr.cov).all():
        # after a refused frame: from +-BASIN_SIGMAS along the fit's weakest direction
        lam, vec = eigh(0.5 * (fr.cov + fr.cov.T))
        step = vec[:, -1] * np.sqrt(max(lam[-1], 0.0)) * BASIN_SIGMAS
        starts += [(f"{BASIN_SIGMAS:g} sigma off", matmul_exact(se3_exp(k * step), T)) for k in (1.0, -1.0)]
    for what, T_alt in starts:
        fr_a = refit(T_alt)
        if not fr_a.healthy or fr_a.T_cam_model is None:
            continue
        T_a = sym(T, fr_a.T_cam_model)
        gap = centre_gap(T, T_a)
        _, deg = pose_error(inv_T(T), inv_T(T_a))
        if gap > b.rel * d or float(deg) > b.deg:
            s0, s1 = float(getattr(fr, "score", np.nan)), float(getattr(fr_a, "score", np.nan))
            if np.isfinite(s0) and np.isfinite(s1) and s1 > s0 + SCORE_MARGIN:
                return "", fr_a
            return (f"{REASON_AMBIGUOUS}: the fit from {what} lies {gap / d:.1%} of the model distance, "
                    f"{float(deg):.2f} deg away (budget {b.rel:.0%}, {b.deg:g} deg)"), None
    return "", None


def is_refusal(reason: str | None) -> bool:
    """Whether a frame's ``reason`` is the error budget's (uncertain or ambiguous)."""
    return (reason or "").startswith((REASON_UNCERTAIN, REASON_AMBIGUOUS))


def _view_samples(fr) -> int:
    """A frame's visible edge samples before the ``max_samples`` cap (the capped count where unknown)."""
    n = int(getattr(fr, "n_visible", -1))
    return n if n >= 0 else int(fr.n_samples)


class Refusals:
    """The error budget's state over a sequence: the frames it refused (``budget_frames``: uncertain,
    ``ambiguous_frames``), whether the last frame was refused (``after``), and the last two frames'
    poses while both were model poses (the motion prediction of :meth:`predicted`)."""

    def __init__(self):
        self.budget_frames: list[int] = []
        self.ambiguous_frames: list[int] = []
        self.after = False
        self.after_uncertain = False  #: the last frame refused as uncertain (RETURN_FRACTION applies)
        #: frames in a row refused by the return fraction alone (within the full budget, a steady
        #: view: RETURN_STEADY_FRAMES), up to the last
        self.steady = 0
        self.within = False  #: the frame being judged counts towards ``steady`` (set by :meth:`judge`)
        self.n_prev: int | None = None  #: the last frame's visible edge samples, uncapped (:meth:`seen`)
        self.model_pair: list[np.ndarray] = []
        #: a frame since the start was not output as a model pose (lost, refused, map pose): from then on
        #: a frame without a motion prediction is also checked from +-BASIN_SIGMAS (:func:`ambiguity`)
        self.broken = False

    def judge(self, b: PoseBudget, fr, distance_m) -> str:
        """Why the edge pose ``fr`` is beyond the budget ``b`` (:func:`beyond_budget`; '' when it is not).
        After an uncertain frame it must lie within ``RETURN_FRACTION`` of it, or within the budget in
        a steady view (``RETURN_STEADY_VIEW``) for ``RETURN_STEADY_FRAMES`` frames in a row, this one
        the last."""
        if not self.after_uncertain:
            return beyond_budget(b, fr.cov, fr.T_cam_model, distance_m)
        why = beyond_budget(b, fr.cov, fr.T_cam_model, distance_m, RETURN_FRACTION)
        n0, n = self.n_prev, _view_samples(fr)
        steady = n0 is not None and n0 > 0 and abs(n - n0) <= RETURN_STEADY_VIEW * n0
        self.within = bool(why) and steady and not beyond_budget(b, fr.cov, fr.T_cam_model, distance_m)
        if self.within and self.steady + 1 >= RETURN_STEADY_FRAMES:
            return ""
        return why

    def seen(self, fr) -> None:
        """Every frame's edge result, whatever its output: its view size for the next frame's steady test."""
        self.n_prev = _view_samples(fr)

    def output(self, status: str, T_out: np.ndarray | None) -> None:
        """A frame's output (not refused): two consecutive model (or relocalised) poses give the
        prediction; any other frame breaks the pair."""
        self.after = self.after_uncertain = self.within = False
        self.steady = 0
        if status in ("model", "relocalised") and T_out is not None:
            self.model_pair = (self.model_pair[-1:] + [T_out])[-2:]
        else:
            self.model_pair = []
            self.broken = True

    def predicted(self) -> np.ndarray | None:
        """Constant-velocity prediction from the last two frames when both were model poses (None otherwise)."""
        if len(self.model_pair) < 2:
            return None
        Ta, Tb = self.model_pair
        return matmul_exact(matmul_exact(Tb, inv_T(Ta)), Tb)

    def refused(self, idx: int, reason: str) -> None:
        """Frame ``idx``'s edge pose refused by the budget (``reason`` uncertain or ambiguous): counted,
        the pair broken, the next frame checked for ambiguity after a refusal."""
        steady = self.steady + 1 if self.within and reason.startswith(REASON_UNCERTAIN) else 0
        self.output("lost", None)
        self.steady = steady
        self.after = True
        self.after_uncertain = reason.startswith(REASON_UNCERTAIN)
        if reason.startswith(REASON_UNCERTAIN):
            self.budget_frames.append(int(idx))
        elif reason.startswith(REASON_AMBIGUOUS):
            self.ambiguous_frames.append(int(idx))
