"""Real-texture ground-truth clips: a public-domain portrait fitted with MediaPipe's 478-point
mesh, moved with known head pose and expressions, and rendered with texture mapping
(see docs/realface.md)."""
