"""The learned body model: shape and expression VAEs, joint centres, pose correctives, skinning.

    from humotion.body import load_body_model
    body = load_body_model("low")                              # or "full" (13,718 vertices)
    shape = body.shape_from_measurements(height=1.8, weight=75)
    out = body(shape=shape, pose=rotations)                    # out.vertices, out.joints; body.faces

Run time (plain torch, no Anny):

- :mod:`~humotion.body.model`: the model (parameters -> vertices, joints, faces), latent sampling
  and interpolation, weight files. Beside it: :mod:`~humotion.body.anthropometry` (height,
  weight and BMI of meshes, the shape of a given height and weight), :mod:`~humotion.body.checks`
  (input checks), the two posing paths :mod:`~humotion.body.cpu_posing` (compiled inference,
  with :mod:`~humotion.body.cpu_kernels`) and :mod:`~humotion.body.torch_posing`
  (differentiable), and :mod:`~humotion.body.derived` (what inference keeps between calls).
- :mod:`~humotion.body.fitting`: pose (and shape) fitting within joint limits to registered
  meshes, 3D joints or 2D keypoints seen by a pinhole camera.
- Components: :mod:`~humotion.body.vae` (PReLU VAEs), :mod:`~humotion.body.joints` (joint
  regressor), :mod:`~humotion.body.correctives` (grouped pose-space deformation),
  :mod:`~humotion.body.skinning` (kinematics, LBS, learned weights), :mod:`~humotion.body.limits`.
- :mod:`~humotion.body.posing`: poses onto the rig (mocap retargeting, canonical skeleton).
- :mod:`~humotion.body.floor`: feet on the floor through a motion, from foot contacts;
  :mod:`~humotion.body.quality`: the standard CMU pose set, regions and edge stretch.

Training and data:

- :mod:`~humotion.body.train`: end-to-end training (``humotion train body``), alternating L-BFGS
  pose re-optimisation with Adam model updates; :mod:`~humotion.body.evaluation`: held-out errors.
- :mod:`~humotion.body.dataset`: registered training meshes generated from the open body model
  Anny (shapes x mocap poses x expressions, two resolutions, one skeleton);
  :mod:`~humotion.body.rest_shapes`: extra subjects' rest shapes; :mod:`~humotion.body.files`:
  the data folder's files; :mod:`~humotion.body.anny_source`: everything that touches Anny (an
  optional extra, ``pip install humotion[anny]``), never used by the shipped model.
"""

from humotion.body.model import BodyModel, BodyOutput, interpolate, load_body_model

__all__ = ["BodyModel", "BodyOutput", "interpolate", "load_body_model"]
