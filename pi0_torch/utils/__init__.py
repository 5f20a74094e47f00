"""Small shared helpers: atomic output folders, the cleanup of dead runs' partial folders, quiet library calls."""
