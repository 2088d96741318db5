"""Everything that crosses the disk: the scene folder reader (design section 2), articulation.json
(section 3), URDF, PLY and the report picture, all written atomically."""
