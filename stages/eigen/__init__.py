"""Eigenfeature analysis of the performer's expression (Valente & Dugelay), a second reading
beside point tracking.

- :mod:`.patches`: feature patches cut in the neutral's frame through the 2D similarity.
- :mod:`.eigenfeatures`: PCA of each feature's patches.
- :mod:`.estimator`: the linear estimator ``L = M Lambda^T (Lambda Lambda^T)^-1``.
- :mod:`.sampling`: the paper's and a richer sampling of parameters and rotations.
- :mod:`.model`: the trained model, the analysis of frames, parameters -> geometry.
- :mod:`.training`: the face-model interface and the training from its renders.
- :mod:`.synthetic`: the fixture generator's performer face as the face model.
- :mod:`.packface`: a real performer's actor pack driven by the synthesis as the face model.
- :mod:`.stage`: ``train.eigenfeatures``, ``analyze.eigenfeatures``.
"""
