"""Pure numpy math of probegrid (no I/O): the layer every other layer builds on."""
