"""Who may act: the users file, the login throttle and the servers' certificates, shared by every
interface that authenticates (the screen, OPC UA). Roles and the command table are in cell.core."""
