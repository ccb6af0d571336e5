"""Drawing primitives apart from the algorithm: OpenCV overlays for nodes, matplotlib figures for reports."""
