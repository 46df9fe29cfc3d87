"""What users read, made from a calibration: reports and plots, certificates, the focal
lengths to use, exports to other software, undistorted images, the fleet's status and
dashboard. The numbers they show (uncertainty, comparisons, change tests, the correction
grid) are computed by :mod:`fieldcal.analysis`.
"""
