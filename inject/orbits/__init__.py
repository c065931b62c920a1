"""Real passes: orbits seen from a site during an exposure, and the tracks they leave."""
