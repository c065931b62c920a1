"""LSSTCam: sensors, the focal-plane layout and its distortion, and every celestial WCS."""
