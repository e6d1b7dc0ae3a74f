package android.content;

public final class AttributionSource {
    private AttributionSource() {
        throw new RuntimeException("Stub!");
    }

    public static final class Builder {
        public Builder(int uid) {
            throw new RuntimeException("Stub!");
        }

        public Builder setPackageName(String value) {
            throw new RuntimeException("Stub!");
        }

        public AttributionSource build() {
            throw new RuntimeException("Stub!");
        }
    }
}
