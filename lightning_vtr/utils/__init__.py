"""Small shared helpers of the package: argument validation, atomic file writes, alpha compositing, image logging, progress feedback."""
