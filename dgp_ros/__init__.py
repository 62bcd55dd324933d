"""dgp_ros: Dissipative Gaussian Processes for passive online damping identification."""
__version__ = '0.1.0'
