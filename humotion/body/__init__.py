"""The learned body model: shape and expression VAEs, joint centres, pose correctives, skinning.

Modules so far:

- :mod:`humotion.body.dataset`: registered training meshes (shapes x mocap poses x expressions,
  two resolutions, one skeleton) generated from the open body model Anny, written to a folder of
  .npz files, and read back (`load_split`, `load_model_file`) without needing Anny.
- :mod:`humotion.body.anny_source`: everything that touches Anny (an optional extra,
  ``pip install humotion[anny]``); used only to build data, never by the shipped model.
"""
