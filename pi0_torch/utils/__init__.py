"""Small shared helpers: atomic output folders and the cleanup of dead runs' partial folders."""
