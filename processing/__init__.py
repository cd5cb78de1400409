"""Pure processing: stitching, 3D mapping, defect detection and their metrics.

Functions here take arrays and return arrays and dataclasses; they never touch the
database or the network. Section, equation and algorithm numbers ("§3.1", "eq. (12)",
"Algorithm 2") refer to the paper the project implements:

    H. M. La, T. H. Dinh, N. H. Pham, Q. P. Ha and A. Q. Pham, "Automated Robotic
    Monitoring and Inspection of Steel Structures and Bridges", Robotica, Cambridge
    University Press, 2016.
"""

from processing.open3d_viewer import defer_plotly_viewer

defer_plotly_viewer()
