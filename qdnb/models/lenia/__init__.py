"""Chapter 5: Flow Lenia with embedded parameters (the simulator of the FLT's datasets)."""
