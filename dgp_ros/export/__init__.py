"""
A frozen model as generated C++ for a real-time controller (no rclpy, no Python at run time).

``export_cpp(path, out)`` writes one self-contained, header-only C++17 file that answers as the
frozen node serving ``path`` answers (docs/CONTRACTS.md, "dgp_ros.export"); ``served_model``
is that model in Python (proven at export as the node proves it); ``ExportError`` says why a
model cannot be exported. The console tool is ``dgp-export`` (``dgp_ros/apps/export.py``).
"""
from .errors import ExportError
from .frozen import check_correction, export_cpp, header_spec, served_model, write_header
from .spec import model_spec, prove_as_node

__all__ = ['export_cpp', 'served_model', 'header_spec', 'write_header', 'check_correction',
           'ExportError', 'model_spec', 'prove_as_node']
