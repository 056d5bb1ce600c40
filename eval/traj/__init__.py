"""mst.eval.traj: trajectory comparison of ``mst eval traj`` (evo-equal ATE/RPE, the UAV table, gaps).

Holds: config (TrajConfig), metrics (association, alignment, errors, yaw), compare (core + file form ->
TrajResult), report (console rows), navtable (the UAV table against a GPS/AHRS log).
May import: numpy, mst.core (trajectory files), mst.errors, mst.pipeline.nav.log (navtable only).

Conventions: poses are ``T_model_cam`` 4x4 float64 (camera pose in the model/world frame, what TUM
files hold); positions in metres, angles in degrees. The computations follow evo (Grupp 2017)
exactly, so the numbers equal ``evo_ape`` / ``evo_rpe`` on the same files:

* association: evo's ``associate_trajectories`` (nearest timestamp within ``t_max_diff_s`` seconds,
  each pose of the trajectory with fewer poses matched into the longer one);
* alignment of the estimate onto the reference: ``none``; ``se3`` / ``sim3`` (Umeyama on the
  associated positions, without / with scale); ``first`` (the estimate's first associated pose
  mapped onto the reference's: ``T = T_ref[0] @ inv(T_est[0])``);
* ATE: ``|t_est - t_ref|`` per associated pose; rotation error: angle of ``R_est^T R_ref``;
* RPE (consecutive pairs chosen on the aligned estimate like evo): ``E = inv(inv(Q_i) Q_j) inv(P_i) P_j``,
  translation norm and rotation angle, for ``delta_frames`` frames and for ``delta_m`` metres of path;
* statistics: rmse, mean, median, std (population), min, max.

UAV table (mean and std of dX dY dZ and d-yaw): differences estimate - reference of the aligned
positions along the model axes (metres), and of the yaw (degrees, wrapped to (-180, 180], after
removing the constant camera-mount offset ``yaw_offset_deg``). **Yaw of a camera pose**: the heading
of the camera's optical axis (its +z axis) projected on the model XY plane, ``atan2(R[1,2], R[0,2])``
in degrees (0 = +X, 90 = +Y). When the optical axis is within 10 degrees of vertical (nadir camera)
the image-up direction (-y axis of the camera) is projected instead.

Gaps: reference poses that have no estimate within ``t_max_diff_s`` (tracking lost), counted and listed
as ranges of consecutive reference indices with their times.
"""

from mst.eval.traj.compare import (
    RelativeError,
    TrajResult,
    TrajSeries,
    compare_trajectories,
    evaluate_trajectories,
)
from mst.eval.traj.config import TrajConfig
from mst.eval.traj.metrics import (
    NADIR_LIMIT_DEG,
    ErrorStats,
    align_estimate,
    associate,
    camera_yaw_deg,
    error_stats,
    gap_ranges,
    rpe,
    rpe_pairs_frames,
    rpe_pairs_metres,
    umeyama,
    wrap_deg,
)
from mst.eval.traj.report import report_rows, uav_rows

__all__ = [
    "NADIR_LIMIT_DEG", "ErrorStats", "RelativeError", "TrajConfig", "TrajResult", "TrajSeries", "align_estimate",
    "associate", "camera_yaw_deg", "compare_trajectories", "error_stats", "evaluate_trajectories", "gap_ranges",
    "report_rows", "rpe", "rpe_pairs_frames", "rpe_pairs_metres", "uav_rows", "umeyama", "wrap_deg",
]
