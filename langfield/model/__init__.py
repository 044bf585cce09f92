"""The model: Gaussians, the hash grids and the colour and language heads read from them."""
