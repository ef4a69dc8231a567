"""What every role shares: status codes, validation, settings, retry, transforms, loop guards,
counters, bounded caches, health rules, master-restart detection. No rospy; see docs/architecture.md."""
