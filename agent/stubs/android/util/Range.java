package android.util;

public final class Range<T extends Comparable<? super T>> {
    public Range(T lower, T upper) {
        throw new RuntimeException("Stub!");
    }

    public T getLower() {
        throw new RuntimeException("Stub!");
    }

    public T getUpper() {
        throw new RuntimeException("Stub!");
    }
}
