"""The ground floor: errors, settings checks, atomic files and output guards, content digests,
the plug-in registries and the stored-value format every room may use (nothing here imports
another room)."""
