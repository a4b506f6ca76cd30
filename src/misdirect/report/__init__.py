"""What a person reads: the paper's reproduction, figures, pictures and the defence report."""
