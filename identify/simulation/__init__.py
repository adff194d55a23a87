"""The hybrid stick/slip simulator, regime maps, and data sets with a withheld effect."""
