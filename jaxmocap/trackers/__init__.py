"""Trackers: the colour-shirt tracker of Wang et al. 2011 and the stereo particle filter of Azad et al. 2007."""
