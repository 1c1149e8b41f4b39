"""Layer 4, applications: detection, reports, exports, undistortion."""
