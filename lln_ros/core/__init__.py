"""The algorithm, importable and testable without rclpy: backbones and their runtime, the LLN
head, landmarks, the extractor, similarity, retrieval (first stage and rerank), the sequence
search, and the matcher's decisions (docs/architecture.md)."""
