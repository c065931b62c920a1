"""inject: realistic, range-defocused satellite streaks for Rubin/LSSTCam images."""
__version__ = "0.1.0"
