"""Small shared helpers of the package: argument validation, atomic file writes, deprecation aliases."""
