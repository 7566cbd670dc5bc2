"""Face landmarks for real performers: MediaPipe's Face Landmarker (478-vertex mesh, blendshapes,
facial transformation matrix) per frame, and the layout's feature points computed from the mesh."""
