"""Stage III: sequence calibration (each view's VIO world put into the scene's world)."""
