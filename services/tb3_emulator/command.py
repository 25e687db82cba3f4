"""``srl tb3-emulator`` / ``python -m services.tb3_emulator``: an emulated TurtleBot3 Burger that
speaks ROS 2 over Zenoh (rmw_zenoh or zenoh-bridge-ros2dds wire), with its own main."""

from __future__ import annotations

import argparse
import json
import time

from common.config.arguments import (
    COMMAND_SETTINGS,
    UsageError,
    add_bridge_arguments,
    add_lifetime_arguments,
    add_settings_arguments,
    floats_arg,
    settings_from_args,
)
from common.contracts.summaries import EmulatorSummary
from common.math.plant_models import PLANT_MODELS
from common.process.runtime import connect_with_retry, own_resources, service_stop

NAME = "tb3-emulator"
HELP = "an emulated TurtleBot3 Burger speaking ROS 2 over Zenoh"

# The emulator's cmd_vel timeout. 0.5 s is the OpenCR firmware's own HEARTBEAT_TIMEOUT_MS (it
# stops the wheels when turtlebot3_node falls silent for 500 ms): five missed 10 Hz commands. At
# 0.22 m/s a broken command path then costs <= 11 cm.
CMD_TIMEOUT_DEFAULT = 0.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, COMMAND_SETTINGS[NAME])
    add_bridge_arguments(parser)
    parser.add_argument(
        "--initial-pose",
        type=floats_arg(3),
        metavar="X,Y,THETA",
        help="start pose in the odom frame (default: the episode start, through bridge.goal)",
    )
    parser.add_argument(
        "--noise",
        type=floats_arg(2),
        default=(0.0, 0.0),
        metavar="SIGMA_XY,SIGMA_THETA",
        help="std. dev. of Gaussian noise on the reported pose [m, rad] (default 0,0)",
    )
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    parser.add_argument("--latency", type=float, default=0.0, help="[s] cmd_vel -> wheels delay (default: 0)")
    parser.add_argument(
        "--cmd-timeout",
        type=float,
        default=CMD_TIMEOUT_DEFAULT,
        help="[s] stop when cmd_vel is older: a robot must stop when its command stream breaks; "
        f"0: hold the last command forever, like a stock TurtleBot3 (default: {CMD_TIMEOUT_DEFAULT})",
    )
    parser.add_argument("--v-max", type=float, help="firmware limit [m/s] (default: the Burger's 0.22)")
    parser.add_argument("--omega-max", type=float, help="firmware limit [rad/s] (default: the Burger's 2.84)")
    parser.add_argument(
        "--model",
        choices=list(PLANT_MODELS),
        help="ideal: wheels reach the command at once, odometry = truth; actuator: a TurtleBot3's wheels "
        "and encoder odometry ([actuator] settings, docs/turtlebot-models.md); physics: a rigid-body TurtleBot3 "
        "in MuJoCo ([physics] settings) (default: the settings' plant.model)",
    )
    parser.add_argument("--odom-rate", type=float, default=20.0, help="[Hz] odometry rate (default: 20)")
    parser.add_argument(
        "--attachment",
        choices=("compact", "legacy"),
        default="compact",
        help="rmw_zenoh attachment format: compact (rmw_zenoh_cpp Humble >= 0.1.2, Jazzy >= 0.2.4) "
        "or legacy (Humble 0.1.0-0.1.1, Jazzy 0.2.0-0.2.3) (default: compact)",
    )
    parser.add_argument(
        "--listen",
        help="be the robot's Zenoh router on this endpoint; transport.secure, users_file and tls_* secure it "
        "as they secure srl router, with the robot's access rules (docs/security.md) (default: connect to --router)",
    )
    parser.add_argument(
        "--localization",
        choices=("none", "tf", "pose_with_covariance", "odometry", "pose_stamped"),
        help="also publish a localization on the bridge's pose topic: the true pose in map "
        "(docs/turtlebot-localization.md) (default: the settings' bridge.pose_source; none for odom)",
    )
    parser.add_argument(
        "--localization-noise",
        type=floats_arg(2),
        default=(0.0, 0.0),
        metavar="SIGMA_XY,SIGMA_THETA",
        help="std. dev. of Gaussian noise on the published localization [m, rad] (default 0,0)",
    )
    parser.add_argument(
        "--localization-update",
        type=floats_arg(2),
        default=(0.25, 0.2),
        metavar="DIST,ANGLE",
        help="AMCL-like sources (pose_with_covariance, tf): a fix after this much motion [m, rad] "
        "(nav2_amcl update_min_d, update_min_a of turtlebot3_navigation2) (default 0.25,0.2)",
    )
    parser.add_argument(
        "--localization-rate",
        type=float,
        default=10.0,
        help="[Hz] streaming sources (odometry, pose_stamped) and /tf (default: 10)",
    )
    add_lifetime_arguments(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:

    import zenoh

    from common.contracts import ros_wire
    from common.contracts.ros_wire import CMD_TYPES, DEFAULT_CMD_TYPE, RosGraph, pose_topic
    from common.math.frames import Pose2D, from_goal_frame
    from common.net.transport import zenoh_config
    from services.robot_bridge.robot_router import robot_router_config
    from services.tb3_emulator.service import LocalizationConfig, Tb3Model, run

    settings = settings_from_args(args)
    bridge = settings.bridge
    if args.initial_pose is not None:
        pose = Pose2D(*args.initial_pose)
    else:  # the episode's start (goal frame) where the bridge's goal puts it in the odom frame
        pose = from_goal_frame(Pose2D(*(float(c) for c in settings.start_state())), Pose2D(*bridge.goal))
    cmd_type = DEFAULT_CMD_TYPE[bridge.ros_distro] if bridge.cmd_type == "auto" else CMD_TYPES[bridge.cmd_type]
    stop = service_stop()  # signals (bounded) and srl up's death
    if args.listen:  # the robot's own Zenoh router (like rmw_zenohd on the robot; secured by [transport])
        session = zenoh.open(robot_router_config(settings, args.listen))
    else:
        session = connect_with_retry(
            lambda: zenoh.open(zenoh_config(settings.transport)), settings, "tb3-emulator", args.connect_timeout, stop
        )
    robot_model = args.model or settings.plant.model
    v_max = ros_wire.TB3_BURGER_V_MAX if args.v_max is None else args.v_max
    omega_max = ros_wire.TB3_BURGER_OMEGA_MAX if args.omega_max is None else args.omega_max
    model = Tb3Model(
        pose,
        v_max,
        omega_max,
        args.latency,
        args.cmd_timeout,
        (args.noise[0], args.noise[1]),
        args.seed,
        time.monotonic(),
        model=robot_model,
        params=settings.turtlebot_params(),
        physics=settings.physics_params(),
    )
    source = args.localization or ("none" if bridge.pose_source == ros_wire.ODOMETRY_ONLY else bridge.pose_source)
    if not (args.localization_rate > 0 and all(c >= 0 for c in (*args.localization_noise, *args.localization_update))):
        raise UsageError("tb3-emulator: --localization-rate must be > 0, its noise and update >= 0")
    localization = (
        None
        if source == "none"
        else LocalizationConfig(
            source,
            pose_topic(bridge.model_copy(update={"pose_source": source})),
            (args.localization_noise[0], args.localization_noise[1]),
            (args.localization_update[0], args.localization_update[1]),
            args.localization_rate,
        )
    )
    try:
        result = run(
            session,
            RosGraph.from_settings(bridge),
            cmd_type,
            model,
            stop,
            args.run_seconds,
            bridge.odom_topic,
            bridge.cmd_vel_topic,
            args.odom_rate,
            attachment=args.attachment,
            localization=localization,
        )
    finally:
        session.close()
    summary = EmulatorSummary.model_validate({**result, "initial_pose": list(pose), "resources": own_resources()})
    print(json.dumps(summary.to_json_dict()), flush=True)
    return 0
