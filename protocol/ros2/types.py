"""The ROS 2 types mfvs publishes and accepts: each one's ROS name and its RIHS01 type hash (REP-2011).

A type hash is the SHA-256 of the type's description (its fields and every nested type's, REP-2011) and goes into
every rmw_zenoh key of the type (keys.py), so a hash that is wrong by one bit hides a topic from ROS 2. Where the
values come from, all recorded in tests/protocol/ros2/fixtures/fixtures.json by make_fixtures.py beside it:

- "package": the type description the ROS 2 Jazzy interface package ships, share/<pkg>/<msg|srv>/<Name>.json
  (ros-jazzy-* wheels: common_interfaces 5.3.6 (sensor_msgs, geometry_msgs among them), builtin_interfaces and rcl_interfaces 2.0.3, std_srvs 5.3.6),
  written by rosidl_generator_type_description: the value rosidl compiles into the type support rmw_zenoh reads;
- "rosbags": rosbags 0.11.9's REP-2011 hasher over its type stores; for every message type here its Jazzy, Kilted
  and Lyrical stores give the same hash, equal to the package's where the package was at hand.

Jazzy and Kilted (and Lyrical) share every value below: none of these definitions changed between them. Humble
computes no hashes (keys.HUMBLE_TYPE_HASH goes in their place).
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RosType:
    name: str    # the ROS 2 name, <package>/<msg|srv>/<Name>
    rihs01: str  # RIHS01_ and the SHA-256 in hex, for Jazzy, Kilted and Lyrical


# Published by the bridge.
# package (sensor_msgs/msg/Image.json) = rosbags
IMAGE = RosType("sensor_msgs/msg/Image",
                "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47")
# package (sensor_msgs/msg/CameraInfo.json) = rosbags
CAMERA_INFO = RosType("sensor_msgs/msg/CameraInfo",
                      "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275")
# package (sensor_msgs/msg/JointState.json) = rosbags
JOINT_STATE = RosType("sensor_msgs/msg/JointState",
                      "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e")
# rosbags only: tf2_msgs has no Jazzy wheel on PyPI to read the package's value from
TF_MESSAGE = RosType("tf2_msgs/msg/TFMessage",
                     "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087")
# package (std_msgs/msg/String.json) = rosbags = rmw_zenoh's design document's chatter example
STRING = RosType("std_msgs/msg/String",
                 "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
# package (diagnostic_msgs/msg/DiagnosticArray.json) = rosbags
DIAGNOSTIC_ARRAY = RosType("diagnostic_msgs/msg/DiagnosticArray",
                           "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e")

# Accepted by the bridge.
# package (std_srvs/srv/Trigger.json) alone: rosbags' stores hold no services, and rosbags hashes
# service_msgs/msg/ServiceEventInfo (which every service's hash covers, REP-2011) differently from the package
# (83f84988... against 41bcbbe0...: its char[16] read as uint8[16]), so it cannot check this one
TRIGGER = RosType("std_srvs/srv/Trigger",
                  "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f")
# package (geometry_msgs/msg/PoseStamped.json) = rosbags
POSE_STAMPED = RosType("geometry_msgs/msg/PoseStamped",
                       "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8")
# package (sensor_msgs/msg/Joy.json) = rosbags: what the ROS joy driver publishes
JOY = RosType("sensor_msgs/msg/Joy",
              "RIHS01_0d356c79cad3401e35ffeb75a96a96e08be3ef896b8b83841d73e890989372c5")
# package (geometry_msgs/msg/TwistStamped.json) = rosbags: MoveIt Servo's Cartesian input
TWIST_STAMPED = RosType("geometry_msgs/msg/TwistStamped",
                        "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64")

# Nested in the above: never a topic's type here, kept to check the codec's types against (test_types.py).
# package (<pkg>/msg/<Name>.json) = rosbags, each
TIME = RosType("builtin_interfaces/msg/Time",
               "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197")
HEADER = RosType("std_msgs/msg/Header",
                 "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01")
REGION_OF_INTEREST = RosType("sensor_msgs/msg/RegionOfInterest",
                             "RIHS01_ad16bcba5f9131dcdba6fbded19f726f5440e3c513b4fb586dd3027eeed8abb1")
VECTOR3 = RosType("geometry_msgs/msg/Vector3",
                  "RIHS01_cc12fe83e4c02719f1ce8070bfd14aecd40f75a96696a67a2a1f37f7dbb0765d")
QUATERNION = RosType("geometry_msgs/msg/Quaternion",
                     "RIHS01_8a765f66778c8ff7c8ab94afcc590a2ed5325a1d9a076ffff38fbce36f458684")
POINT = RosType("geometry_msgs/msg/Point",
                "RIHS01_6963084842a9b04494d6b2941d11444708d892da2f4b09843b9c43f42a7f6881")
TWIST = RosType("geometry_msgs/msg/Twist",
                "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a")
POSE = RosType("geometry_msgs/msg/Pose",
               "RIHS01_d501954e9476cea2996984e812054b68026ae0bfae789d9a10b23daf35cc90fa")
TRANSFORM = RosType("geometry_msgs/msg/Transform",
                    "RIHS01_beb83fbe698636351461f6f35d1abb20010c43d55374d81bd041f1ba2581fddc")
TRANSFORM_STAMPED = RosType("geometry_msgs/msg/TransformStamped",
                            "RIHS01_0a241f87d04668d94099cbb5ba11691d5ad32c2f29682e4eb5653424bd275206")
KEY_VALUE = RosType("diagnostic_msgs/msg/KeyValue",
                    "RIHS01_d68081eaa540288c5440753baecef0c4e16e81a5f78ad68902ded5100413bb42")
DIAGNOSTIC_STATUS = RosType("diagnostic_msgs/msg/DiagnosticStatus",
                            "RIHS01_b0e3e692ea2d54a8af2f4ef1930e81556a2db55216b771f8a7d2724ed47bf0e4")

#: every type above by its ROS name
BY_NAME: dict[str, RosType] = {value.name: value for value in list(globals().values()) if isinstance(value, RosType)}
