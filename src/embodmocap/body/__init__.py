"""Body model: SMPL adapter and the generated test model.

- :mod:`embodmocap.body.model`: :class:`BodyModel` (skinning via smplx), :func:`load_body_model`,
  :func:`params_for_world_frame`, :class:`BodyOutput`.
- :mod:`embodmocap.body.joints`: SMPL joint names and tree, the SMPL -> COCO-17 mapping.
- :mod:`embodmocap.body.pkl`: reading SMPL ``.pkl`` / ``.npz`` files without chumpy.
- :mod:`embodmocap.body.testmodel`: the generated model in the SMPL file layout.

The torch-based names are imported on first use, so ``import embodmocap.body`` stays light.
"""

from embodmocap.body.joints import SMPL_JOINT_NAMES, SMPL_PARENTS, smpl_to_coco17
from embodmocap.body.pkl import load_model_arrays
from embodmocap.body.testmodel import make_test_model, write_test_model

_LAZY = {"BodyModel", "BodyOutput", "load_body_model", "params_for_world_frame"}

__all__ = [
    "SMPL_JOINT_NAMES", "SMPL_PARENTS", "smpl_to_coco17", "load_model_arrays", "make_test_model",
    "write_test_model", *sorted(_LAZY),
]


def __getattr__(name: str):
    if name in _LAZY:
        from embodmocap.body import model

        return getattr(model, name)
    raise AttributeError(f"module 'embodmocap.body' has no attribute {name!r}")
