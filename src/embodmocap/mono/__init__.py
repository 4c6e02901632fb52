"""The monocular pipeline (``embodmocap mono``): from one view's video, a camera path, coloured
scene points and world SMPL motion in a metric, Z-up world, following the paper's supplement
("More Details of Monocular Human-Scene Reconstruction Pipeline").

Modules: :mod:`.config` (settings), :mod:`.roles` (scene and human models), :mod:`.files`
(inputs users bring, outputs), :mod:`.stitch` (chunk alignment), :mod:`.scale` (metric scale from
the body), :mod:`.gravity` (Z-up), :mod:`.body` (body into the world), :mod:`.stage` (the
resumable command), :mod:`.evaluate` (``<v>_mono_*`` evaluation keys).
"""
