"""Spatial resamplers: nearest, bilinear, bicubic, Lanczos-2, and OpenCV's resize as baselines."""
