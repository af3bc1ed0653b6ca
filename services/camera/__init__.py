"""camera: a real camera, a video file or a folder of images on the camera keys, with its calibration."""
