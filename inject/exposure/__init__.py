"""The whole exposure: focal-plane scenes, their plan, one CCD of them, the runner, the mosaic."""
