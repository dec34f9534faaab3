"""Process setup for the tools: XLA:CPU flags and devices (`cpu`) and the persistent compilation cache
(`compile_cache`). Nothing here runs at import time."""
