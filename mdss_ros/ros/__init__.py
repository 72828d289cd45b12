"""ROS message conversion and input checking for the node (mdss_ros.node).

`convert` turns simulator arrays into messages (large ones straight from numpy bytes);
`validate` turns incoming messages into checked arrays or an InputRejected with a reason.
Only these modules and node.py import ROS message packages; the library never does.
"""
