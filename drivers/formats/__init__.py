"""Readers and writers of depth recordings, one module per format: depthnav's own
(``recording``, ``recording_writer``), bare arrays (``npy``, ``npz``: read member by member),
PNG/PGM folders and TUM RGB-D sets (``png_folder``, with single images in ``depth_images``, which
files are depth in ``image_kinds``, the TUM layout in ``tum``), fakenect folders (``fakenect``),
OpenNI ``.oni`` files (``oni``) and ROS 1/2 bags (``rosbag``, with the depth messages decoded in
``ros_decode`` and image_transport's compressedDepth in ``compressed_depth``)."""
