"""Photos as pixels: reading and writing 8-bit and linear images with their
metadata, colour encoding, and foreground segmentation."""
