"""The communication model: the wireless channel (3GPP path loss), association
of vehicles with edge servers with handover, transfer times over wireless
and wireline links, and the federation's clock that runs them on SUMO's
mobility.

May import: core, sumo.
"""
