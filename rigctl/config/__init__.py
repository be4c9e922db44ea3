"""The rig config and its sections: links, frames, specs, the chamber, notifications, suspenders."""
