"""c4d_core: the floor every package stands on; it imports nothing of the project and no torch.

`config` (YAML presets, overrides), `errors` (`UserError`), `files` (atomic writes), `system`
(EGL check), `geometry` (numpy camera and rigid-body maths), `draw` (colour maps, track overlays,
layouts) and `video` (image and video files).
"""
