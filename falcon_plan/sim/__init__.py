"""The simulated Falcon: plant, validation controller, step experiment."""
