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
    forward_with_status,
    open_tree,
    solve,
    tree_frames,
)
from jaxcal.closure.planar import planar_robot
from jaxcal.closure.table import closure_from_rows
from jaxcal.closure.track import CLOSED, OTHER_MODE, STATUS_NAMES, UNCLOSED

__all__ = ["all_frames", "closed", "CLOSED", "CLOSED_TOL", "Closure", "closure_from_rows", "closure_residual", "closure_status",
           "ClosureSolution", "constraint_jacobian", "FAIL_OFFSET", "failed_pose", "forward_closed", "forward_with_status",
           "Mobility", "mobility", "open_tree", "OTHER_MODE", "planar_robot", "solve", "STATUS_NAMES", "tree_frames", "UNCLOSED",
           "VERDICTS"]
