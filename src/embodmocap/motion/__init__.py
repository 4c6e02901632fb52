"""Stage IV: world-space motion optimisation (SMPLify) and contact alignment."""
