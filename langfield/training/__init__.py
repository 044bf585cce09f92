"""Training a field: the loop, densification, start points and the losses (LAD, LOP, regularisers)."""
