"""The imitation network and how it learns: the model, local training and
evaluation, the trainers that train many vehicles' models, FedAvg, and
checkpoints that load weights only.

May import: core, sumo, links, vision, data.
"""
