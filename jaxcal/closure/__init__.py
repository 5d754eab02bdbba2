"""Loop closure for closed mechanisms (seed 004 ch. 2): LM closure with implicit differentiation,
planar absolute-angle bodies, mobility analysis. See docs/closure.md."""

from jaxcal.closure.analysis import VERDICTS, Mobility, constraint_jacobian, mobility
from jaxcal.closure.core import (
    CLOSED_TOL,
    FAIL_OFFSET,
    Closure,
    ClosureSolution,
    all_frames,
    closed,
    closure_residual,
    closure_status,
    failed_pose,
    forward_closed,
    open_tree,
    solve,
    tree_frames,
)
from jaxcal.closure.planar import planar_robot
from jaxcal.closure.track import CLOSED, OTHER_MODE, STATUS_NAMES, UNCLOSED
from jaxcal.closure.table import closure_from_rows

__all__ = ["CLOSED", "CLOSED_TOL", "FAIL_OFFSET", "OTHER_MODE", "STATUS_NAMES", "UNCLOSED", "closure_status", "failed_pose", "VERDICTS", "Closure", "ClosureSolution", "Mobility", "all_frames", "closed",
           "closure_from_rows", "closure_residual", "constraint_jacobian", "forward_closed", "mobility", "open_tree",
           "planar_robot", "solve", "tree_frames"]
