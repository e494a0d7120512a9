"""crchfl-sumo: hierarchical federated learning for end-to-end driving on SUMO."""

__version__ = "0.1.0"
