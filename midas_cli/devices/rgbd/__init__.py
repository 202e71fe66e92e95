"""RGB-D: a ZED Mini stereo camera (UVC side-by-side, or the Stereolabs SDK), depth by OpenCV StereoSGBM
from the factory calibration, a synthetic stereo camera with known geometry, and hand keypoints."""
