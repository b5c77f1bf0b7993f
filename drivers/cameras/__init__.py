"""Frame sources: a camera device or URL, a video file, a folder of images, the simulation."""
