"""Interactive expression editor (Zhang et al., TVCG 2006, Sec. 10, 13, 14.2).

An animator drags feature points of the target face in a browser; motion propagation infers the
most likely positions of all the others and expression synthesis renders the image with its
details while dragging. Keyframes are exported as a points file that the pipeline renders like a
performance (``editor/render_keyframes.yaml``). Start it with ``expression-editor --pack PACK``
(:mod:`editor.cli`); the page is served by :mod:`editor.server`.
"""
