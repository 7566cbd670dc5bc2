"""Actor packs built from footage (paper Sec. 5, 8, 10, 14): frame filters, frame selection, pack writing."""
