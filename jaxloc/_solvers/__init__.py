"""Overhead-camera pose solvers: Lambda Twist P3P and the paper's linear Eq. 6."""

from .dlt import paper_linear_pose as paper_linear_pose, PoseSolution as PoseSolution
from .p3p import p3p as p3p, P3PSolution as P3PSolution
