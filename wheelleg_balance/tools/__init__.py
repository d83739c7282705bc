"""Command-line tools: experiments, benchmark, main job, fault report."""
