"""What is made from a calibration: reports and plots, uncertainty maps, comparisons,
exports to other software, undistorted images.
"""
