"""OSVI-WM: encoder, action and world models, waypoint head, losses, training, planning, latent decoder."""
