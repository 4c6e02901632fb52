"""Test-wide settings."""

import os

# Before anything imports open3d or torch: OpenMP threads sleep instead of spin-waiting, which
# on a 2-core machine running two pytest workers is the difference between seconds and minutes.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
