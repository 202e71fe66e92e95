"""RGB-D: a ZED Mini stereo camera (UVC side-by-side, or the Stereolabs SDK), depth by OpenCV StereoSGBM
from the factory calibration, the simulated camera over the synthetic stereo camera
(:mod:`midas_cli.synthetic.stereo_camera`), and hand keypoints."""
