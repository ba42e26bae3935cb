"""Shared by every test package: the scene and file helpers of this folder
(``rosbag_scenes``, ``cloud_scenes``, ``modelfiles``, ``blendweights``, ``fuzzing``) are
imported by name from the test modules of ``tests/<package>/``; pytest puts this folder on
``sys.path`` when it loads this file."""
