"""Jobs: the commands' work, composed from the library (filter, bake, export, ...)."""
