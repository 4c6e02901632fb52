"""Body model: SMPL adapter and the generated test model."""
