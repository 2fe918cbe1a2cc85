"""Core math: numpy and scipy only, no I/O, no printing."""
