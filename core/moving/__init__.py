"""Unsupervised moving-object detection from 3D flow: components, saliency, box fit, NMS."""
