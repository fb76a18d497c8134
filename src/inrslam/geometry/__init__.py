"""Camera geometry and SE(3): rays, projection, pose parameterisations, axis conventions."""
