"""The simulated Falcon: plant, compiled-function calls, step experiment."""
