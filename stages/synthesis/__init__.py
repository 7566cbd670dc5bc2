"""Expression synthesis (Zhang et al. 2006, Sec. 5-8, 11): QP, warp, build, compositing, stages. See docs/synthesis.md."""
