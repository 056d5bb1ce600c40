"""Model-based tracking (``mst track``): the one-frame edge tracker, the session and its policy, the runner.
May import mst.core, mst.errors, mst.meshtools and the other mst.pipeline modules (frames, depth_io, slam, fusion).

Modules: :mod:`.config` (TrackConfig and the ViSP XML map), :mod:`.visibility`, :mod:`.moving_edges`,
:mod:`.vvs` (the per-frame kernels), :mod:`.edge_tracker` (one frame), :mod:`.health` (image
evidence, calibrated health score), :mod:`.session` (``TrackingSession.step -> FrameRecord``,
``TrackingPolicy``), :mod:`.relocalise`, :mod:`.edgelets` / :mod:`.render_edges` (edges from renders),
:mod:`.overlay`, :mod:`.runner` (``run_track``: files in, files out, a ``TrackSummary``).
"""

from mst.pipeline.tracking.config import EdgesConfig, TrackConfig, read_tracker_xml, visp_xml_settings
from mst.pipeline.tracking.edge_tracker import EdgeTracker, FrameResult
from mst.pipeline.tracking.health import HealthMonitor, PoseEvidence
from mst.pipeline.tracking.runner import TrackSummary, check_pose_in_view, run_track
from mst.pipeline.tracking.session import FrameRecord, TrackingPolicy, TrackingSession

__all__ = ["EdgeTracker", "EdgesConfig", "FrameRecord", "FrameResult", "HealthMonitor", "PoseEvidence", "TrackConfig",
           "TrackSummary", "TrackingPolicy", "TrackingSession", "check_pose_in_view",
           "read_tracker_xml", "run_track", "visp_xml_settings"]
