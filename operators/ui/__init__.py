"""The user interface: the LMDP panel and the policy gizmos."""
