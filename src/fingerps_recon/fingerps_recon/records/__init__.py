"""The records integrators exchange for a print (no ROS): WSQ images (``wsq_image``)."""
