"""Sources of raw samples: captures, emulated nodes and hardware bridges."""
