"""Hand-written GPU kernels that XLA calls through its FFI (built with nvcc on first use; off unless switched on)."""
