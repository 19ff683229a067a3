"""Where a ROS 2 topic travels over Zenoh, as a settings section (the services' ROS 2 inputs and outputs)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from services.codec import ros2


class Ros2Topic(BaseModel):
    """One ROS 2 topic on the rmw_zenoh key (with its attachment when published) or the zenoh-bridge-ros2dds key."""

    model_config = ConfigDict(extra="forbid")

    topic: str = Field(description="ROS 2 topic (relative to namespace)")
    namespace: str = Field("", description="ROS 2 namespace, e.g. /jackal")
    domain_id: int = Field(0, ge=0, description="ROS_DOMAIN_ID (rmw_zenoh key prefix)")
    key_style: ros2.KeyStyle = Field("rmw_zenoh", description="rmw_zenoh key or zenoh-bridge-ros2dds key")
    distro: ros2.Distro = Field("jazzy", description="message definitions (and type hash) of this ROS 2 distro")
    key: str | None = Field(None, description="explicit Zenoh key (overrides the fields above)")

    def key_expr(self, ros_type: str, subscribe: bool = False) -> str:
        """The key to publish `ros_type` on, or with `subscribe` the key expression to receive it on: any type
        hash, so a publisher of another distro's definitions still matches."""
        if self.key:
            return self.key
        return ros2.topic_key(self.topic, ros_type, self.namespace, self.domain_id, self.key_style, self.distro,
                              hash_wildcard=subscribe)
