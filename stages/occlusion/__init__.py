"""Occlusion of face regions, judged from the image: a hand or object over the mouth, an eye, a
brow or the nose, where a face landmarker goes on guessing the points."""
