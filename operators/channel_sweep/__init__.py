"""Sweeping the tags' channels: the labelling operator and the channel plan."""
