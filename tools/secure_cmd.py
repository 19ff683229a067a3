"""`gpmppi secure init DIR` and `gpmppi secure check DIR`: Zenoh credentials and access control for the stack."""

from __future__ import annotations

from pathlib import Path

import typer

from tools.cli_checks import DIR, OUT_DIR, only_with

ROS2_CMD_KEY = "0/cmd_vel/*/*"  # rmw_zenoh: <domain>/<topic>/<type>/<hash>, Twist or TwistStamped
ROS2_ODOM_KEY = "0/odometry/filtered/*/*"
# deploy/ros2_nav2.yaml's: Nav2's path and goal (the nav service reads them), the planner's plan out
ROS2_NAV_KEYS = {"path": "0/plan/*/*", "goal": "0/goal_pose/*/*", "costmap": "0/local_costmap/costmap/*/*",
                 "plan": "0/local_plan/*/*"}


def register(app: typer.Typer) -> None:
    """Add `gpmppi secure init` and `gpmppi secure check`."""
    secure_app = typer.Typer(help="Authentication, access control and TLS for the Zenoh router.", no_args_is_help=True)

    @secure_app.command("init")
    def init(
        directory: Path = typer.Argument(
            ..., metavar=OUT_DIR, help="folder to write the secrets to (created, mode 700)"
        ),
        robot: str = typer.Option("jackal", "--robot", help="robot name in every key the rules name"),
        tls: bool = typer.Option(
            False,
            "--tls",
            help="also make a CA, a router certificate and client certificates (mTLS) for off-robot links",
        ),
        host: list[str] = typer.Option(
            ["localhost", "127.0.0.1"],
            "--host",
            help="name or address the router is reached at over TLS (repeat; goes in its certificate)",
        ),
        endpoint: str = typer.Option("tcp/127.0.0.1:7447", help="router endpoint written into the configs"),
        tls_endpoint: str = typer.Option("tls/127.0.0.1:7448", help="router TLS endpoint (with --tls)"),
        ros2: bool = typer.Option(
            False,
            "--ros2",
            help="the router is the robot's rmw_zenoh router: add a "
            "'ros2' identity for its ROS 2 nodes and the ROS 2 keys egress, ingress, nav and the planner use",
        ),
        ros2_cmd_key: str = typer.Option(ROS2_CMD_KEY, help="with --ros2: the base's command key (only egress)"),
        ros2_odom_key: str = typer.Option(ROS2_ODOM_KEY, help="with --ros2: the odometry key ingress reads"),
        force: bool = typer.Option(False, "--force", help="replace existing secrets (rotates every identity)"),
    ) -> None:
        """Write a users dictionary, one client config per identity, a router config with deny-by-default
        access control, and (--tls) certificates. Re-running with --force rotates everything."""
        from services.security.secure import ROLES, SecretsError, init_secrets
        from services.security.secure_check import check_secrets

        only_with(tls, "--tls", {"--tls-endpoint": tls_endpoint != "tls/127.0.0.1:7448",
                                 "--host": list(host) != ["localhost", "127.0.0.1"]})
        only_with(ros2, "--ros2", {"--ros2-cmd-key": ros2_cmd_key != ROS2_CMD_KEY,
                                   "--ros2-odom-key": ros2_odom_key != ROS2_ODOM_KEY})
        keys = {"cmd": ros2_cmd_key, "odom": ros2_odom_key, **ROS2_NAV_KEYS} if ros2 else None
        try:
            written = init_secrets(directory, robot, tls, endpoint, tls_endpoint, host, keys, force)
            check_secrets(directory, robot)  # what was written passes the launch's own check
        except SecretsError as exc:
            typer.echo(f"gpmppi secure init: {exc}", err=True)
            raise typer.Exit(2) from None
        typer.echo(f"wrote {len(written)} files to {directory.resolve()} for robot {robot!r}:")
        for identity, role in ROLES.items():
            typer.echo(f"  {identity + '.json5':<16} {role.description}")
        if ros2:
            typer.echo(f"  {'ros2.json5':<16} the robot's ROS 2 nodes (ZENOH_SESSION_CONFIG_URI)")
        typer.echo(
            "  router.json5     the router: usrpwd + access control (deny by default)"
            + (", TLS/mTLS listener" if tls else "")
        )
        typer.echo(f"run it: gpmppi launch deploy/sim-secure.yaml --secrets {directory}")

    @secure_app.command("check")
    def check(
        directory: Path = typer.Argument(..., metavar=DIR, help="secrets folder made by `gpmppi secure init`"),
        robot: str = typer.Option("jackal", "--robot", help="robot name the launch drives"),
    ) -> None:
        """Check a secrets folder as a launch does (files, users, certificates, access control)."""
        from services.security.secure import SecretsError
        from services.security.secure_check import check_secrets

        try:
            found = check_secrets(directory, robot)
        except SecretsError as exc:
            typer.echo(f"gpmppi secure check: {exc}", err=True)
            raise typer.Exit(2) from None
        typer.echo(f"{found.directory}: {len(found.users)} identities, TLS {'on' if found.tls else 'off'}; ok")

    app.add_typer(secure_app, name="secure")
