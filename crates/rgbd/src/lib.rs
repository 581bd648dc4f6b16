//! rgbd placeholder replaced by the camera work
