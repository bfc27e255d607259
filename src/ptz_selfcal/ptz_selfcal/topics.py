"""The topic and bag contract of ptz_selfcal (DESIGN.md section 3). Every node, tool and test uses these.

The suite runs in the camera's namespace (NAMESPACE, /ptz by default; one suite per camera, e.g. /cam1),
where a driver's image_raw lives, so every name below is relative to it except DIAGNOSTICS (absolute, as
ROS's diagnostics tools expect). In bags the names are stored resolved in the default namespace
(bag_topic: /ptz/image_raw, /ptz/selfcal/camera_info, ...), as bags recorded elsewhere have them.
IMAGE_RELAY (+ CAMERA_INFO beside it) is the camera pair an image_transport CameraSubscriber such as
image_proc finds: frame_ingest republishes each ingested image there, header and bytes unchanged
(IMAGE_RELAY_COMPRESSED when the input transport is compressed).

Input (a live camera, or a bag from `ptz-selfcal synth`):
- IMAGE_RAW: sensor_msgs/Image (mono8, bgr8, rgb8, mono16), or IMAGE_COMPRESSED: sensor_msgs/CompressedImage
  (format "jpeg", "png" or image_transport's "bgr8; jpeg compressed bgr8"); header.frame_id "ptz_camera";
  stamps are capture times.
- JOINT_STATES: sensor_msgs/JointState with names "pan", "tilt" (radians) and "zoom" (raw encoder units,
  focal length grows monotonically with it) at the encoder's own rate, with its own time offset and noise.

Ground truth (synthetic bags only; the pipeline never subscribes to it):
- GT_CAMERA_INFO: one CameraInfo per image, the image's header: true K, P = [K|0], R = I, full-resolution
  width/height. distortion_model GT_DIVISION_MODEL with D = [lambda] when the lens is distorted: the
  division model of camera/distortion.py, lambda on the normalised radius r = |x - c| / fx with the centre c
  at the principal point; otherwise "plumb_bob" with D = [0, 0, 0, 0, 0].
- GT_JOINT_STATES: one JointState per image, the image's stamp: the exact (noise- and lag-free) pan and
  tilt in radians and zoom encoder value.

Pipeline (ptz_selfcal_msgs):
- FRAME_IN: IngestedFrame (working-resolution mono8 image + encoders at the image stamp).
- HOMOGRAPHY: HomographyStamped, one per frame; KEYFRAMES: KeyframeMatches for the bundle adjustment.
- CAMERA_INFO: sensor_msgs/CameraInfo, exactly one per processed image, header copied from the image,
  full-resolution width/height, K, P = [K|0], R = I, plumb_bob D = [k1, k2, 0, 0, 0].
- FRAME_CALIBRATION: FrameCalibration (status, uncertainty, orientation, encoders), one per image. sigma_f
  is an honest 1-sigma that includes the sequence's common scale error (section 6.2). Status (message
  constants, never renumbered): INITIALISING (K from the prior), CALIBRATING, CONVERGED (a promise:
  |fx - f| <= 3 sigma_f in >= 95 % of CONVERGED frames and none more than 1 % off), DEGENERATE_MOTION
  (the motion does not determine the calibration, section 6; the reason in the log), MODEL_MISMATCH (the
  keyframe matches fit the lens model far worse than the tracker's noise: distortion not modelled, a
  rolling shutter; never CONVERGED), TRACKING_LOST (last good K), PREDICTED_FROM_ZOOM (the zoom model's K).
- ORIENTATION: geometry_msgs/TransformStamped per frame whose orientation is known, the image's stamp:
  the camera (child_frame) in the calibration's reference frame (reference_frame), rotation only (tf2_msgs
  for /tf is not among this environment's packages; a tf relay can republish it).
- DIAGNOSTICS: diagnostic_msgs/DiagnosticArray.
"""

NAMESPACE = "/ptz"
IMAGE_RAW = "image_raw"
IMAGE_COMPRESSED = "image_raw/compressed"
JOINT_STATES = "joint_states"
GT_CAMERA_INFO = "ground_truth/camera_info"
GT_JOINT_STATES = "ground_truth/joint_states"
GT_MOVING_MASK = "ground_truth/moving_mask"  # mono8 Image per image, same header: 255 on moving objects
FRAME_IN = "selfcal/frame_in"
HOMOGRAPHY = "selfcal/homography"
KEYFRAMES = "selfcal/keyframes"
CAMERA_INFO = "selfcal/camera_info"
FRAME_CALIBRATION = "selfcal/frame"
MOSAIC = "selfcal/mosaic"  # sensor_msgs/CompressedImage: the live mosaic (nodes/mosaic_node.py)
ORIENTATION = "selfcal/orientation"  # geometry_msgs/TransformStamped: the camera in the reference frame
IMAGE_RELAY = "selfcal/image_raw"
IMAGE_RELAY_COMPRESSED = "selfcal/image_raw/compressed"
DIAGNOSTICS = "/diagnostics"

CAMERA_FRAME_ID = "ptz_camera"
JOINT_NAMES = ("pan", "tilt", "zoom")
GT_DIVISION_MODEL = "division"

TYPES = {
    IMAGE_RAW: "sensor_msgs/msg/Image",
    IMAGE_COMPRESSED: "sensor_msgs/msg/CompressedImage",
    JOINT_STATES: "sensor_msgs/msg/JointState",
    GT_CAMERA_INFO: "sensor_msgs/msg/CameraInfo",
    GT_JOINT_STATES: "sensor_msgs/msg/JointState",
    GT_MOVING_MASK: "sensor_msgs/msg/Image",
    FRAME_IN: "ptz_selfcal_msgs/msg/IngestedFrame",
    HOMOGRAPHY: "ptz_selfcal_msgs/msg/HomographyStamped",
    KEYFRAMES: "ptz_selfcal_msgs/msg/KeyframeMatches",
    CAMERA_INFO: "sensor_msgs/msg/CameraInfo",
    FRAME_CALIBRATION: "ptz_selfcal_msgs/msg/FrameCalibration",
    ORIENTATION: "geometry_msgs/msg/TransformStamped",
    IMAGE_RELAY: "sensor_msgs/msg/Image",
    IMAGE_RELAY_COMPRESSED: "sensor_msgs/msg/CompressedImage",
    DIAGNOSTICS: "diagnostic_msgs/msg/DiagnosticArray",
}


def resolve(name: str, namespace: str = NAMESPACE) -> str:
    """The absolute name of a topic in `namespace` (absolute names stay as they are)."""
    if name.startswith("/"):
        return name
    ns = namespace.strip("/")
    return f"/{ns}/{name}" if ns else f"/{name}"


def bag_topic(name: str) -> str:
    """The topic name as stored in bags: resolved in the default namespace."""
    return resolve(name, NAMESPACE)
