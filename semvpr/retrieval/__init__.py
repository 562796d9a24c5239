"""The retrieval task: frozen-trunk feature stores, mining, losses, the retriever LightningModule, its
DataModule, Recall@N and the data-parallel plumbing. Stands on ``models``, ``data``, ``segmentation``
and ``core``; never reads a config."""
