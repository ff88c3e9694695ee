"""World modeling: the node cycle, predictions, What Is / What If, the command line and the API."""
